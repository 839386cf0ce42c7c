//! Initial values and shapes of a scene, on a line or in a box: shapes,
//! analytic presets and `.npy` files.
//!
//! Positions: in a box, cell `(i, j)` has its centre at `(i + ½, j + ½)`
//! (unit cells; in 3D `(i + ½, j + ½, k + ½)`); on a line, value `i` sits at `x = i·dx` (the grid points of
//! a periodic line, as in benchmark P1).

use std::f64::consts::TAU;
use std::path::Path;

use diffsim_solvers::exact::on_faces;
use diffsim_solvers::flow::Shape;
use diffsim_solvers::smoke::MacGrid;
use diffsim_solvers::smoke::{Solid, enforce_boundary, solid_cells};

use super::spec::{InitSpec, NpyPaths, ShapeSpec};
use super::value::{finite, positive};
use super::{Domain, Field, SceneError};

/// A point with one coordinate per axis of the domain.
fn point(key: &str, v: &[f64], dims: usize) -> Result<Vec<f64>, SceneError> {
    if v.len() != dims {
        let want = ["[x]", "[x, y]", "[x, y, z]"][dims.clamp(1, 3) - 1];
        return Err(SceneError::key(key, format!("expected {want} for a {dims}D domain, got {} value(s)", v.len())));
    }
    for x in v {
        finite(key, *x)?;
    }
    Ok(v.to_vec())
}

/// A box's corners `lower` and `upper` under `key`, one coordinate per
/// axis, `upper` above `lower` on every axis.
fn box_corners(key: &str, lower: &[f64], upper: &[f64], dims: usize) -> Result<(Vec<f64>, Vec<f64>), SceneError> {
    let (a, b) = (point(&format!("{key}.lower"), lower, dims)?, point(&format!("{key}.upper"), upper, dims)?);
    if let Some(axis) = (0..dims).find(|&d| a[d] >= b[d]) {
        let name = ["x", "y", "z"][axis];
        return Err(SceneError::key(format!("{key}.upper"), format!("must exceed `lower` on every axis: on {name}, upper {} ≤ lower {}", b[axis], a[axis])));
    }
    Ok((a, b))
}

/// A 2D shape as a body ([`Shape`]: a box becomes a polygon), checked to be
/// a proper one (a positive radius, a simple polygon).
pub(super) fn shape_of(key: &str, shape: &ShapeSpec) -> Result<Shape, SceneError> {
    let xy = |k: &str, v: &[f64]| point(&format!("{key}.{k}"), v, 2).map(|p| [p[0], p[1]]);
    let body = match shape {
        ShapeSpec::Box { lower, upper } => {
            let (a, b) = box_corners(key, lower, upper, 2)?;
            let (a, b) = ([a[0], a[1]], [b[0], b[1]]);
            Shape::Polygon { vertices: vec![a, [b[0], a[1]], b, [a[0], b[1]]] }
        }
        ShapeSpec::Disc { center, radius } => Shape::Circle { center: xy("center", center)?, radius: positive(&format!("{key}.radius"), *radius)? },
        ShapeSpec::Fourier { center, r0, cos, sin } => {
            Shape::Fourier { center: xy("center", center)?, r0: finite(&format!("{key}.r0"), *r0)?, cos: cos.clone(), sin: sin.clone() }
        }
        ShapeSpec::Polygon { vertices } => {
            Shape::Polygon { vertices: vertices.iter().enumerate().map(|(k, v)| xy(&format!("vertices[{k}]"), v)).collect::<Result<_, _>>()? }
        }
        ShapeSpec::Sphere { .. } | ShapeSpec::Cylinder { .. } | ShapeSpec::Npy(_) => return Err(only_3d(key)),
    };
    body.check().map_err(|e| SceneError::key(key, e.to_string()))?;
    Ok(body)
}

/// The error for a 3D shape elsewhere.
fn only_3d(key: &str) -> SceneError {
    SceneError::key(key, "sphere, cylinder and npy shapes need a 3D domain (size = [nx, ny, nz])")
}

/// An axis by name (`x`, `y`, `z`), or an error at `key`.
pub(super) fn axis_of(key: &str, name: &str) -> Result<usize, SceneError> {
    crate::volume::axis_index(name).ok_or_else(|| SceneError::key(key, crate::words::unknown("axis", name, &crate::volume::AXES)))
}

/// The solid cells of a shape in a box of `D` axes (a cell is solid when
/// its centre lies inside; `npy`, 3D: where the file's value is not zero),
/// or `None` when no cell is: one function for 2D and 3D, each shape
/// refused with its reason in the dimension it does not exist in.
fn box_shape_cells<const D: usize>(key: &str, cfg: &MacGrid<D>, shape: &ShapeSpec, dir: &Path) -> Result<Option<Vec<bool>>, SceneError> {
    let at = |k: &str| format!("{key}.{k}");
    let corner = |v: &[f64]| -> [f64; D] { std::array::from_fn(|a| v[a]) };
    let solid = match shape {
        ShapeSpec::Box { lower, upper } => {
            let (a, b) = box_corners(key, lower, upper, D)?;
            Solid::Box { lower: corner(&a), upper: corner(&b) }
        }
        ShapeSpec::Sphere { .. } | ShapeSpec::Cylinder { .. } | ShapeSpec::Npy(_) if D != 3 => return Err(only_3d(key)),
        ShapeSpec::Disc { .. } if D != 2 => return Err(SceneError::key(key, "a disc is 2D; in 3D use a sphere or a cylinder")),
        ShapeSpec::Disc { center, radius } | ShapeSpec::Sphere { center, radius } => {
            let c = point(&at("center"), center, D)?;
            Solid::Ball { center: corner(&c), radius: positive(&at("radius"), *radius)? }
        }
        ShapeSpec::Cylinder { center, radius, axis, extent } => {
            let c = point(&at("center"), center, D)?;
            let axis = axis_of(&at("axis"), axis)?;
            let extent = match extent {
                None => [f64::NEG_INFINITY, f64::INFINITY],
                Some(e) => {
                    let e = point(&at("extent"), e, 2).map_err(|_| SceneError::key(at("extent"), "expected [from, to] along the axis"))?;
                    if e[0] >= e[1] {
                        return Err(SceneError::key(at("extent"), format!("`to` {} must exceed `from` {}", e[1], e[0])));
                    }
                    [e[0], e[1]]
                }
            };
            Solid::Cylinder { axis, center: corner(&c), radius: positive(&at("radius"), *radius)?, extent }
        }
        ShapeSpec::Npy(path) => {
            // The file's axes slowest first.
            let shape: Vec<u64> = cfg.n.iter().rev().map(|&m| m as u64).collect();
            let full = dir.join(path);
            let fail = |why: String| SceneError::key(at("npy"), format!("{}: {why}", full.display()));
            let bytes = crate::files::read_bytes(&full, 8 * cfg.n_s() as u64 + 65_536, "`.npy` obstacle mask").map_err(|e| fail(e.to_string()))?;
            let values = npy_values(&bytes, &shape).map_err(fail)?;
            // Not "wholly outside": the mask is inside, it marks nothing.
            if values.iter().all(|&v| v == 0.0) {
                return Err(fail("every value is zero: the mask marks no solid cell (solid where a value is not zero)".into()));
            }
            return Ok(Some(values.iter().map(|&v| v != 0.0).collect()));
        }
        ShapeSpec::Fourier { .. } | ShapeSpec::Polygon { .. } if D != 2 => return Err(SceneError::key(key, "Fourier and polygon shapes need a 2D domain")),
        ShapeSpec::Fourier { .. } | ShapeSpec::Polygon { .. } => {
            let body = shape_of(key, shape)?;
            let (nx, ny) = (cfg.n[0], cfg.n[1]);
            let cells: Vec<bool> = (0..nx * ny).map(|c| body.level((c % nx) as f64 + 0.5, (c / nx) as f64 + 0.5) < 0.0).collect();
            return Ok(cells.contains(&true).then_some(cells));
        }
    };
    let cells = solid_cells(cfg, &[solid]);
    Ok(cells.contains(&true).then_some(cells))
}

/// The cells (values, on a line) inside a shape, clipped to the domain; a
/// shape wholly outside is an error. `dir` is where `.npy` paths start.
pub(super) fn shape_cells(key: &str, domain: &Domain, shape: &ShapeSpec, dir: &Path) -> Result<Vec<bool>, SceneError> {
    let dims = domain.dims();
    let cells = match (domain, shape) {
        (Domain::Box(cfg), _) => box_shape_cells(key, cfg, shape, dir)?,
        (Domain::Box3(cfg), _) => box_shape_cells(key, cfg, shape, dir)?,
        (Domain::Line(_), ShapeSpec::Sphere { .. } | ShapeSpec::Cylinder { .. } | ShapeSpec::Npy(_)) => return Err(only_3d(key)),
        (Domain::Line(_), ShapeSpec::Fourier { .. } | ShapeSpec::Polygon { .. }) => {
            return Err(SceneError::key(key, "Fourier and polygon shapes need a 2D domain"));
        }
        (Domain::Line(l), ShapeSpec::Box { lower, upper }) => {
            let (a, b) = box_corners(key, lower, upper, dims)?;
            let (a, b) = (a[0], b[0]);
            let cells: Vec<bool> = (0..l.n).map(|i| (a..b).contains(&(i as f64 * l.dx))).collect();
            cells.iter().any(|&c| c).then_some(cells)
        }
        (Domain::Line(l), ShapeSpec::Disc { center, radius }) => {
            let c = point(&format!("{key}.center"), center, dims)?[0];
            let r = positive(&format!("{key}.radius"), *radius)?;
            let cells: Vec<bool> = (0..l.n).map(|i| (i as f64 * l.dx - c).abs() <= r).collect();
            cells.iter().any(|&c| c).then_some(cells)
        }
    };
    cells.ok_or_else(|| {
        let size = match domain {
            Domain::Box(cfg) => format!("{}×{} domain", cfg.n[0], cfg.n[1]),
            Domain::Box3(cfg) => format!("{}×{}×{} domain", cfg.n[0], cfg.n[1], cfg.n[2]),
            Domain::Line(l) => format!("domain [0, {})", l.n as f64 * l.dx),
        };
        SceneError::key(key, format!("the shape lies wholly outside the {size}"))
    })
}

/// The initial value (or loss target) of `field` from its spec: the
/// field's slice of the packed state. `dir` is where `.npy` paths start.
pub(super) fn field_init(key: &str, domain: &Domain, field: Field, init: &InitSpec, dir: &Path) -> Result<Vec<f64>, SceneError> {
    let len = domain.range(field).len();
    let dims = domain.dims();
    let mut values = match (init, field, domain) {
        (InitSpec::Zero, _, _) => vec![0.0; len],
        (InitSpec::Npy(paths), _, _) => read_npy(key, domain, field, paths, dir)?,
        (InitSpec::Disc { center, radius, value }, Field::Smoke, _) | (InitSpec::Disc { center, radius, value }, Field::Velocity, Domain::Line(_)) => {
            let value = finite(&format!("{key}.value"), *value)?;
            let cells = shape_cells(key, domain, &ShapeSpec::Disc { center: center.clone(), radius: *radius }, dir)?;
            cells.into_iter().map(|c| if c { value } else { 0.0 }).collect()
        }
        (InitSpec::Box { lower, upper, value }, Field::Smoke, _) | (InitSpec::Box { lower, upper, value }, Field::Velocity, Domain::Line(_)) => {
            let value = finite(&format!("{key}.value"), *value)?;
            let cells = shape_cells(key, domain, &ShapeSpec::Box { lower: lower.clone(), upper: upper.clone() }, dir)?;
            cells.into_iter().map(|c| if c { value } else { 0.0 }).collect()
        }
        (InitSpec::Sphere { center, radius, value }, Field::Smoke, Domain::Box3(_)) => {
            let value = finite(&format!("{key}.value"), *value)?;
            let cells = shape_cells(key, domain, &ShapeSpec::Sphere { center: center.clone(), radius: *radius }, dir)?;
            cells.into_iter().map(|c| if c { value } else { 0.0 }).collect()
        }
        (InitSpec::Sphere { .. }, Field::Smoke, _) => return Err(only_3d(key)),
        (InitSpec::Sine { amplitude, wavenumber }, _, _) => {
            let a = finite(&format!("{key}.sine.amplitude"), *amplitude)?;
            let k = point(&format!("{key}.sine.wavenumber"), wavenumber, dims)?;
            sine(domain, field, a, &k)
        }
        (InitSpec::Uniform(v), Field::Velocity, _) => {
            let v = point(&format!("{key}.uniform"), v, dims)?;
            match domain {
                Domain::Line(_) => vec![v[0]; len],
                Domain::Box(cfg) => {
                    let mut uv = vec![v[0]; cfg.n_vel()];
                    uv[cfg.n_face(0)..].fill(v[1]);
                    uv
                }
                Domain::Box3(cfg) => (0..3).flat_map(|a| std::iter::repeat_n(v[a], cfg.n_face(a))).collect(),
            }
        }
        (InitSpec::Uniform(_), Field::Smoke, _) => return Err(SceneError::key(key, "`uniform` is for the velocity; use a shape, `sine`, `npy` or \"zero\"")),
        (InitSpec::TaylorGreen(a), Field::Velocity, Domain::Box(cfg)) => {
            let a = finite(&format!("{key}.taylor_green"), *a)?;
            let (lx, ly) = (cfg.n[0] as f64, cfg.n[1] as f64);
            let k = [TAU / lx, TAU / ly];
            on_faces(
                cfg.n,
                1.0,
                |axis, [x, y]| {
                    if axis == 0 { a * (k[0] * x).sin() * (k[1] * y).cos() } else { -a * (ly / lx) * (k[0] * x).cos() * (k[1] * y).sin() }
                },
            )
        }
        (InitSpec::Abc(a), Field::Velocity, Domain::Box3(cfg)) => {
            let a = finite(&format!("{key}.abc"), *a)?;
            let k = cfg.n.map(|m| TAU / m as f64);
            on_faces(cfg.n, 1.0, |axis, [x, y, z]| {
                let (x, y, z) = (k[0] * x, k[1] * y, k[2] * z);
                a * [z.sin() + y.cos(), x.sin() + z.cos(), y.sin() + x.cos()][axis]
            })
        }
        (InitSpec::TaylorGreen(_), _, _) => return Err(SceneError::key(key, "`taylor_green` is a 2D velocity (size = [nx, ny])")),
        (InitSpec::Abc(_), _, _) => return Err(SceneError::key(key, "`abc` is a 3D velocity (size = [nx, ny, nz])")),
        (InitSpec::Disc { .. } | InitSpec::Box { .. } | InitSpec::Sphere { .. }, Field::Velocity, Domain::Box(_)) => {
            return Err(SceneError::key(key, "a 2D velocity starts \"zero\", `uniform = [vx, vy]`, `sine` or `npy = [u, v]`"));
        }
        (InitSpec::Disc { .. } | InitSpec::Box { .. } | InitSpec::Sphere { .. }, Field::Velocity, Domain::Box3(_)) => {
            return Err(SceneError::key(key, "a 3D velocity starts \"zero\", `uniform = [vx, vy, vz]`, `sine` or `npy = [u, v, w]`"));
        }
        (InitSpec::Sphere { .. }, Field::Velocity, Domain::Line(_)) => return Err(only_3d(key)),
    };
    match (field, domain) {
        (Field::Velocity, Domain::Box(cfg)) => enforce_boundary(cfg, &mut values),
        (Field::Velocity, Domain::Box3(cfg)) => enforce_boundary(cfg, &mut values),
        _ => {}
    }
    // A finite amplitude can still evaluate to NaN (a sine of wavenumber
    // 1e308): refused here, before any step samples it.
    if let Some(at) = values.iter().position(|v| !v.is_finite()) {
        return Err(SceneError::key(
            key,
            format!("evaluates to {} at sample {at} of the {} (flat index); every value must be finite", values[at], field.name()),
        ));
    }
    Ok(values)
}

/// `a·sin(2π·k·x/L)` at the field's sample positions.
fn sine(domain: &Domain, field: Field, a: f64, k: &[f64]) -> Vec<f64> {
    match domain {
        Domain::Line(l) => {
            let len = l.n as f64 * l.dx;
            (0..l.n).map(|i| a * (TAU * k[0] * i as f64 * l.dx / len).sin()).collect()
        }
        Domain::Box(cfg) => {
            let (n, ny) = (cfg.n[0], cfg.n[1]);
            // `k` periods across the box along each axis.
            let at = |x: f64, y: f64| a * (TAU * (k[0] * x / n as f64 + k[1] * y / ny as f64)).sin();
            match field {
                Field::Smoke => (0..cfg.n_s()).map(|c| at((c % n) as f64 + 0.5, (c / n) as f64 + 0.5)).collect(),
                Field::Velocity => {
                    let mut out = Vec::with_capacity(cfg.n_vel());
                    for j in 0..ny {
                        for i in 0..=n {
                            out.push(at(i as f64, j as f64 + 0.5));
                        }
                    }
                    for j in 0..=ny {
                        for i in 0..n {
                            out.push(at(i as f64 + 0.5, j as f64));
                        }
                    }
                    out
                }
            }
        }
        Domain::Box3(cfg) => {
            let n = cfg.n;
            // `k` periods across the box along each axis.
            let at = |p: [f64; 3]| a * (TAU * (0..3).map(|b| k[b] * p[b] / n[b] as f64).sum::<f64>()).sin();
            // Samples of the centres (axis 3) or of the faces normal to an axis.
            let lattice = |axis: usize| {
                let e: Vec<usize> = (0..3).map(|b| n[b] + (b == axis) as usize).collect();
                let o = move |b: usize| if b == axis { 0.0 } else { 0.5 };
                (0..e[0] * e[1] * e[2]).map(move |c| [(c % e[0]) as f64 + o(0), ((c / e[0]) % e[1]) as f64 + o(1), (c / (e[0] * e[1])) as f64 + o(2)])
            };
            match field {
                Field::Smoke => lattice(3).map(at).collect(),
                Field::Velocity => (0..3).flat_map(lattice).map(at).collect(),
            }
        }
    }
}

/// The values of a `.npy` file's bytes: C order, float64 or float32 (read
/// as float64), of exactly `shape` (numpy order), every value finite.
pub fn npy_values(bytes: &[u8], shape: &[u64]) -> Result<Vec<f64>, String> {
    flat_header(bytes)?;
    let npy = npyz::NpyFile::new(bytes).map_err(|e| format!("not a valid .npy file: {e}"))?;
    if npy.order() == npyz::Order::Fortran {
        return Err("Fortran order; save it in C order (numpy's default)".into());
    }
    if npy.shape() != shape {
        return Err(format!("shape {:?}, expected {:?} (rows = y, columns = x)", npy.shape(), shape));
    }
    let dtype = npy.dtype().descr();
    let values: Vec<f64> = match dtype.as_str() {
        "'<f8'" => npy.into_vec::<f64>().map_err(|e| format!("cannot read the values: {e}"))?,
        "'<f4'" => npy.into_vec::<f32>().map_err(|e| format!("cannot read the values: {e}"))?.into_iter().map(f64::from).collect(),
        other => return Err(format!("dtype {other}; expected float64 or float32")),
    };
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(format!("value {i} (flat index) is {}", values[i]));
    }
    Ok(values)
}

/// Refuses a `.npy` header that is not flat (one dictionary, one shape
/// tuple, no lists) or whose shape does not multiply to a storable count. npyz parses the header (a Python literal) with
/// backtracking that takes exponential time in nested brackets (found by
/// fuzzing: a 190-byte header of nested braces ran for over 20 s); the
/// float arrays read here never nest.
fn flat_header(bytes: &[u8]) -> Result<(), String> {
    if bytes.len() < 10 || !bytes.starts_with(b"\x93NUMPY") {
        return Ok(()); // not a .npy file: npyz says so
    }
    let (start, len) = match bytes[6] {
        1 => (10, usize::from(u16::from_le_bytes([bytes[8], bytes[9]]))),
        _ if bytes.len() >= 12 => (12, u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize),
        _ => return Ok(()),
    };
    let header = &bytes[start.min(bytes.len())..start.saturating_add(len).min(bytes.len())];
    let count = |c: u8| header.iter().filter(|&&b| b == c).count();
    if count(b'{') > 1 || count(b'(') > 1 || count(b'[') > 0 {
        return Err("not a valid .npy file: its header nests brackets (an array of float64 or float32 has one flat dictionary)".into());
    }
    // npyz multiplies the shape's sizes unchecked (found by fuzzing: a size
    // of 10¹⁹ overflowed); they must multiply to a count that fits.
    let text = String::from_utf8_lossy(header);
    if let Some(dims) = text.split_once('(').and_then(|(_, r)| r.split_once(')')).map(|(d, _)| d) {
        let product = dims.split(',').map(str::trim).filter(|d| !d.is_empty()).try_fold(1u64, |n, d| d.parse::<u64>().ok().and_then(|d| n.checked_mul(d)));
        if product.is_none_or(|n| n > 1 << 48) {
            return Err(format!("not a valid .npy file: its shape ({}) is not a list of sizes of a storable array", crate::files::shorten(dims, 80)));
        }
    }
    Ok(())
}

/// The field's values from `.npy` files, one per array of the field (C
/// order, float64 or float32, the shapes of [`Domain::arrays`]).
fn read_npy(key: &str, domain: &Domain, field: Field, paths: &NpyPaths, dir: &Path) -> Result<Vec<f64>, SceneError> {
    let arrays = domain.arrays(field);
    let paths = paths.list();
    let key = format!("{key}.npy");
    if paths.len() != arrays.len() {
        let want = if arrays.len() == 1 { "one file".to_string() } else { format!("{} files [u, v]", arrays.len()) };
        return Err(SceneError::key(key, format!("expected {want} for the {} of a {}D domain, got {}", field.name(), domain.dims(), paths.len())));
    }
    let mut out = Vec::with_capacity(domain.range(field).len());
    for (path, array) in paths.iter().zip(&arrays) {
        let full = dir.join(path);
        let fail = |why: String| SceneError::key(key.clone(), format!("{}: {why}", full.display()));
        // At most the array in float64 and a header: larger files are not this array.
        let limit = 8 * array.range.len() as u64 + 65_536;
        let bytes = crate::files::read_bytes(&full, limit, "`.npy` array of this field").map_err(|e| SceneError::key(key.clone(), e.to_string()))?;
        let values = npy_values(&bytes, &array.shape).map_err(fail)?;
        out.extend(values);
    }
    Ok(out)
}
