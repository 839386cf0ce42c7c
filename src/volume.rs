//! Pictures of 3D fields (arrays `[k][j][i]`, x fastest, as P4 and 3D
//! scenes store them): a slice at any index along any axis and the
//! maximum-intensity projection along an axis, each a 2D image seen from
//! the positive end of that axis.
//!
//! Image axes (right, up) of a view along each axis: along z, (x, y); along
//! y, (x, z); along x, (z, y). Images are row-major with row 0 at the
//! bottom.

/// The axes' names, by index.
pub const AXES: [&str; 3] = ["x", "y", "z"];

/// An axis by name: `"x"`, `"y"`, `"z"`.
pub fn axis_index(name: &str) -> Option<usize> {
    AXES.iter().position(|&a| a == name)
}

/// A 2D image: `values[row·width + column]`, row 0 at the bottom.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Values, row-major.
    pub values: Vec<f64>,
}

/// The (right, up) axes of a view along `axis`.
pub fn view_axes(axis: usize) -> (usize, usize) {
    match axis {
        0 => (2, 1),
        1 => (0, 2),
        _ => (0, 1),
    }
}

/// Flat index of `(i, j, k)` in an array of extents `dims = [nx, ny, nz]`.
fn at(dims: [usize; 3], q: [usize; 3]) -> usize {
    (q[2] * dims[1] + q[1]) * dims[0] + q[0]
}

/// Calls `f(pixel, q)` for every pixel of a view along `axis` and every
/// cell `q` on its ray (in order along the axis).
fn rays(dims: [usize; 3], axis: usize, mut f: impl FnMut(usize, [usize; 3])) {
    let (r, u) = view_axes(axis);
    for row in 0..dims[u] {
        for col in 0..dims[r] {
            for d in 0..dims[axis] {
                let mut q = [0; 3];
                q[r] = col;
                q[u] = row;
                q[axis] = d;
                f(row * dims[r] + col, q);
            }
        }
    }
}

/// The plane `index` along `axis` of the field `f` of extents `dims`.
///
/// # Panics
/// If `f` does not have `nx·ny·nz` values, `axis > 2` or `index` is past
/// the field along `axis`.
pub fn slice(dims: [usize; 3], f: &[f64], axis: usize, index: usize) -> Image {
    assert!(f.len() == dims.iter().product::<usize>() && axis < 3 && index < dims[axis], "volume::slice: lengths");
    let (r, u) = view_axes(axis);
    let mut values = vec![0.0; dims[r] * dims[u]];
    rays(dims, axis, |pixel, q| {
        if q[axis] == index {
            values[pixel] = f[at(dims, q)];
        }
    });
    Image { width: dims[r], height: dims[u], values }
}

/// The maximum of `f` along `axis` at every pixel (maximum-intensity
/// projection).
///
/// # Panics
/// As [`slice`].
pub fn max_projection(dims: [usize; 3], f: &[f64], axis: usize) -> Image {
    assert!(f.len() == dims.iter().product::<usize>() && axis < 3, "volume::max_projection: lengths");
    let (r, u) = view_axes(axis);
    let mut values = vec![f64::NEG_INFINITY; dims[r] * dims[u]];
    rays(dims, axis, |pixel, q| values[pixel] = values[pixel].max(f[at(dims, q)]));
    Image { width: dims[r], height: dims[u], values }
}

/// Whether any cell along each ray is marked (obstacles' silhouettes).
pub fn any_projection(dims: [usize; 3], marked: &[bool], axis: usize) -> Vec<bool> {
    let (r, u) = view_axes(axis);
    let mut out = vec![false; dims[r] * dims[u]];
    rays(dims, axis, |pixel, q| out[pixel] |= marked[at(dims, q)]);
    out
}

/// The marked cells of the plane `index` along `axis`.
pub fn slice_marks(dims: [usize; 3], marked: &[bool], axis: usize, index: usize) -> Vec<bool> {
    let f: Vec<f64> = marked.iter().map(|&m| m as u8 as f64).collect();
    slice(dims, &f, axis, index).values.iter().map(|&v| v != 0.0).collect()
}
