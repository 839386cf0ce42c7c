//! From a parsed scene file to a [`Scene`]: every value checked, the step
//! built from exactly the declared effects.

use std::path::Path;

use diffsim_solvers::boundary::{Boundary, Profile, Side};
use diffsim_solvers::burgers::Burgers1d;
use diffsim_solvers::smoke::{MacGrid, Preconditioner, Scheme};
use toml::Spanned;

use super::init::{axis_of, field_init, shape_cells};
use super::spec::{EffectSpec, SceneFile, ShapeSpec};
use super::value::{count, finite, iterations, positive, tolerance};
use super::{Array, Control, Domain, Field, Line, Scene, SceneError, SceneLoss};
use crate::fluids::{Advect, AdvectUpwind, Buoyancy, Diffuse, DiffuseExplicit, DiffuseImplicit, Force, Inflow, Project};
use crate::navier_stokes::{NavierStokes, Viscosity};
use crate::op::{AddParams, Chain, Effect, Part};
use crate::problems::burgers::BurgersEnzyme;
use crate::problems::smoke::SmokeAdvect;
use crate::words::unknown;

/// The 1-based line of byte offset `at` in `text`.
fn line_of(text: &str, at: usize) -> usize {
    text[..at.min(text.len())].bytes().filter(|&b| b == b'\n').count() + 1
}

/// `e`, placed at the line where `spanned` starts.
pub(super) fn placed<S>(text: &str, spanned: &Spanned<S>, e: SceneError) -> SceneError {
    e.at_line(line_of(text, spanned.span().start))
}

/// Runs `f`, placing its error at the line where `span` starts.
pub(super) fn at<T, S>(text: &str, spanned: &Spanned<S>, f: impl FnOnce(&S) -> Result<T, SceneError>) -> Result<T, SceneError> {
    f(spanned.get_ref()).map_err(|e| placed(text, spanned, e))
}

/// The `[domain]` of a scene stepped in time.
fn domain(file: &SceneFile, text: &str) -> Result<Domain, SceneError> {
    at(text, &file.domain, |d| {
        let size = &d.size;
        match size.len() {
            1 => {
                let n = count("domain.size[0]", size[0])?;
                if n < 3 {
                    return Err(SceneError::key("domain.size", format!("need at least 3 cells, got {n}")));
                }
                grid_fits(&[n as u64], LINE_ARRAYS)?;
                let length = positive("domain.length", d.length.unwrap_or(n as f64))?;
                let periodic = match &d.boundary {
                    None => false,
                    Some(toml::Value::String(s)) if s == "periodic" => true,
                    Some(toml::Value::String(s)) if s == "closed" => false,
                    Some(_) => return Err(SceneError::key("domain.boundary", "a line is \"periodic\" or \"closed\" (no flux)")),
                };
                Ok(Domain::Line(Line { n, dx: length / n as f64, periodic }))
            }
            2 => {
                let (nx, ny) = (count("domain.size[0]", size[0])?, count("domain.size[1]", size[1])?);
                if nx.min(ny) < 4 {
                    return Err(SceneError::key("domain.size", format!("need at least 4 cells per side, got [{nx}, {ny}]")));
                }
                grid_fits(&[nx as u64 + 1, ny as u64 + 1], BOX_ARRAYS)?;
                if d.length.is_some() {
                    return Err(SceneError::key("domain.length", "a box has unit cells; `length` is for 1D domains"));
                }
                let boundary = domain_boundary(d)?;
                boundary.validate().map_err(|e| SceneError::key("domain.boundary", e.to_string()))?;
                Ok(Domain::Box(MacGrid::new([nx, ny]).with_boundary(boundary)))
            }
            3 => {
                let [nx, ny, nz] = [0, 1, 2].map(|a| count(&format!("domain.size[{a}]"), size[a]));
                let (nx, ny, nz) = (nx?, ny?, nz?);
                if nx.min(ny).min(nz) < 4 {
                    return Err(SceneError::key("domain.size", format!("need at least 4 cells per side, got [{nx}, {ny}, {nz}]")));
                }
                grid_fits(&[nx as u64 + 1, ny as u64 + 1, nz as u64 + 1], BOX_ARRAYS)?;
                if d.length.is_some() {
                    return Err(SceneError::key("domain.length", "a box has unit cells; `length` is for 1D domains"));
                }
                let boundary = match &d.boundary {
                    None => Boundary::<3>::CLOSED,
                    Some(v) => Boundary { sides: <[[Side; 2]; 3]>::try_from(boundary_sides(v, 3)?).expect("three axes") },
                };
                boundary.validate().map_err(|e| SceneError::key("domain.boundary", e.to_string()))?;
                Ok(Domain::Box3(MacGrid::new([nx, ny, nz]).with_dt(1.0).with_boundary(boundary)))
            }
            k => Err(SceneError::key("domain.size", format!("expected [n] (1D), [nx, ny] (2D) or [nx, ny, nz] (3D), got {k} value(s)"))),
        }
    })
}

/// Arrays of the grid's size a scene holds at most while it runs (the
/// state, the step's output, the effects' work: the pressure solve's
/// vectors and multigrid levels are most of it), per cell of a box and of
/// a line: the memory estimate checked before anything is allocated.
pub(super) const BOX_ARRAYS: u64 = 24;
/// See [`BOX_ARRAYS`].
pub(super) const LINE_ARRAYS: u64 = 16;

/// The longest rollout a scene declares (`time.steps`): longer ones would
/// run for days (split them into several runs, each from the last state).
pub const MAX_STEPS: i64 = 10_000_000;

/// The most cell updates a scene may ask for (cells × steps): at about
/// 10⁸ a second on two cores, 10¹² is three hours.
pub const MAX_CELL_STEPS: u64 = 1_000_000_000_000;

/// Refuses a grid of `sizes` whose `arrays` arrays exceed the memory budget.
fn grid_fits(sizes: &[u64], arrays: u64) -> Result<(), SceneError> {
    let cells: Vec<String> = sizes.iter().map(u64::to_string).collect();
    let mut counts = sizes.to_vec();
    counts.push(arrays);
    crate::memory::check("the scene's grid", format!("{arrays} arrays of {} float64 values", cells.join("×")), crate::memory::f64s(&counts), None)
        .map_err(|e| SceneError::key("domain.size", e.to_string()))
}

/// A 2D box's `domain.boundary` (default closed).
pub(super) fn domain_boundary(d: &super::spec::DomainSpec) -> Result<Boundary, SceneError> {
    match &d.boundary {
        None => Ok(Boundary::CLOSED),
        Some(v) => Ok(Boundary { sides: <[[Side; 2]; 2]>::try_from(boundary_sides(v, 2)?).expect("two axes") }),
    }
}

pub(super) fn build(file: SceneFile, text: &str, dir: &Path) -> Result<Scene, SceneError> {
    let Some(time) = &file.time else {
        return Err(SceneError::key("time", "missing: a scene is stepped in time ([time]) or steady ([steady])"));
    };
    at(text, &file.domain, |d| match d.cell {
        Some(_) => Err(SceneError::key("domain.cell", "a scene stepped in time has unit cells; `cell` is for steady scenes")),
        None => Ok(()),
    })?;
    let mut domain = domain(&file, text)?;
    let (dt, steps) = at(text, time, |t| {
        if t.steps > MAX_STEPS {
            return Err(SceneError::key("time.steps", format!("{} steps is more than the {MAX_STEPS} a scene may run; split the run", t.steps)));
        }
        Ok((positive("time.dt", t.dt)?, count("time.steps", t.steps)?))
    })?;
    match &mut domain {
        Domain::Box(cfg) => cfg.dt = dt,
        Domain::Box3(cfg) => cfg.dt = dt,
        Domain::Line(_) => {}
    }
    let cells = domain.range(Field::Smoke).len() as u64;
    if cells.saturating_mul(steps as u64) > MAX_CELL_STEPS {
        return Err(SceneError::key(
            "time.steps",
            format!(
                "{steps} steps of {cells} cells is more than the {MAX_CELL_STEPS:e} cell updates a scene may run (hours at the least); split the run or coarsen the grid"
            ),
        ));
    }

    // Obstacles.
    let mut solid: Option<Vec<bool>> = None;
    for (k, shape) in file.obstacles.iter().enumerate() {
        let cells = at(text, shape, |shape| {
            if domain.dims() == 1 {
                return Err(SceneError::key(format!("obstacles[{k}]"), "obstacles need a 2D or 3D domain"));
            }
            shape_cells(&format!("obstacles[{k}]"), &domain, shape, dir)
        })?;
        let all = solid.get_or_insert_with(|| vec![false; cells.len()]);
        for (a, c) in all.iter_mut().zip(cells) {
            *a |= c;
        }
    }
    if let (Some(all), Some(last)) = (&solid, file.obstacles.last())
        && all.iter().all(|&c| c)
    {
        return Err(placed(text, last, SceneError::key("obstacles", "the obstacles cover every cell of the domain: no fluid is left to simulate")));
    }
    if let (Some(all), Some(last)) = (&solid, file.obstacles.last()) {
        use diffsim_solvers::boundary::sealed_region;
        let sealed = match &domain {
            Domain::Box(cfg) => sealed_region([cfg.n[0], cfg.n[1]], &cfg.boundary, all).map(|r| (r.cells, r.at.to_vec())),
            Domain::Box3(cfg) => sealed_region(cfg.n, &cfg.boundary, all).map(|r| (r.cells, r.at.to_vec())),
            Domain::Line(_) => None,
        };
        if let Some((cells, at)) = sealed {
            let at: Vec<String> = at.iter().map(usize::to_string).collect();
            return Err(placed(
                text,
                last,
                SceneError::key(
                    "obstacles",
                    format!(
                        "the obstacles cut off {cells} fluid cells (the region of cell [{}]) that the inflow feeds and no outflow side drains: no divergence-free flow exists there; open a path to an outflow side",
                        at.join(", ")
                    ),
                ),
            ));
        }
    }

    // Initial state.
    let mut x0 = vec![0.0; domain.n_state()];
    let mut fields = Vec::new();
    // (One field at a time: a by-value array of (enum, reference) pairs
    // crashes Enzyme's type analysis in this crate; docs/pitfalls.md.)
    let mut declare = |field: Field, spec: &Option<Spanned<super::spec::FieldSpec>>| -> Result<(), SceneError> {
        if let Some(spec) = spec {
            let values = at(text, spec, |f| field_init(&format!("fields.{}.init", field.name()), &domain, field, &f.init, dir))?;
            x0[domain.range(field)].copy_from_slice(&values);
            fields.push(field);
        }
        Ok(())
    };
    declare(Field::Smoke, &file.fields.smoke)?;
    declare(Field::Velocity, &file.fields.velocity)?;

    // Effects, in order.
    let mut b = Builder {
        domain,
        dt,
        x0: &x0,
        fields: &fields,
        solid: solid.as_deref(),
        ops: Vec::new(),
        params: Vec::new(),
        named: Vec::new(),
        controls: Vec::new(),
        effects: Vec::new(),
        projected: false,
    };
    for (k, table) in file.effects.iter().enumerate() {
        at(text, table, |table| b.effect(k, table))?;
    }
    if b.ops.is_empty() {
        return Err(SceneError::key("effects", "the scene declares no effect"));
    }
    if solid.is_some() && !b.projected {
        return Err(SceneError::key("obstacles", "obstacles need a pressure effect (no flow through solids is enforced by the projection)"));
    }

    // Loss.
    let loss = match &file.loss {
        None => None,
        Some(l) => Some(at(text, l, |l| {
            let l = match super::spec::loss(l)? {
                super::spec::LossSpec::Field(l) => l,
                super::spec::LossSpec::Force { .. } => {
                    return Err(SceneError::key("loss.kind", "a drag or lift loss needs a steady scene ([steady] in place of [time])"));
                }
            };
            let field = match l.field.as_str() {
                "smoke" => Field::Smoke,
                "velocity" => Field::Velocity,
                other => return Err(SceneError::key("loss.field", unknown("field", other, &["smoke", "velocity"]))),
            };
            // An undeclared field never changes: its loss would be a
            // constant with a zero gradient.
            if !fields.contains(&field) {
                return Err(SceneError::key(
                    "loss.field",
                    format!("the scene declares no {0} field ([fields.{0}]): a loss on it would be a constant with a zero gradient", field.name()),
                ));
            }
            let target = field_init("loss.target", &domain, field, &l.target, dir)?;
            let mut at_steps = match &l.steps {
                None => vec![steps],
                Some(list) if list.is_empty() => return Err(SceneError::key("loss.steps", "lists no step")),
                Some(list) => list
                    .iter()
                    .map(|&t| {
                        if t >= 1 && t as usize <= steps {
                            Ok(t as usize)
                        } else {
                            Err(SceneError::key("loss.steps", format!("step {t} is outside 1..={steps}")))
                        }
                    })
                    .collect::<Result<Vec<_>, _>>()?,
            };
            at_steps.sort_unstable();
            at_steps.dedup();
            let known: Vec<&str> = ["smoke.init", "velocity.init"]
                .into_iter()
                .chain(b.named.iter().map(|(s, _, _)| s.as_str()))
                .chain(b.controls.iter().map(|c| c.name.as_str()))
                .collect();
            for w in &l.with_respect_to {
                if !known.contains(&w.as_str()) {
                    return Err(SceneError::key("loss.with_respect_to", unknown("input", w, &known)));
                }
            }
            Ok(SceneLoss { field, target, steps: at_steps, with_respect_to: l.with_respect_to.clone() })
        })?),
    };
    let Builder { ops, params, named, controls, effects, .. } = b;
    Ok(Scene { domain, dt, steps, step: Chain::new(ops), params, named, controls, effects, fields, x0, solid, loss })
}

/// The effects built so far and what they need to know.
struct Builder<'a> {
    domain: Domain,
    dt: f64,
    x0: &'a [f64],
    fields: &'a [Field],
    solid: Option<&'a [bool]>,
    ops: Vec<Box<dyn Effect>>,
    params: Vec<f64>,
    named: Vec<(String, usize, f64)>,
    controls: Vec<Control>,
    effects: Vec<String>,
    projected: bool,
}

impl Builder<'_> {
    fn has(&self, f: Field) -> bool {
        self.fields.contains(&f)
    }

    /// Names the next parameter `kind.param` (first such effect) and
    /// `effects[k].param`.
    fn name(&mut self, k: usize, kind: &str, param: &str, factor: f64) {
        let index = self.params.len();
        let short = format!("{kind}.{param}");
        if !self.named.iter().any(|(n, _, _)| *n == short) {
            self.named.push((short, index, factor));
        }
        self.named.push((format!("effects[{k}].{param}"), index, factor));
    }

    /// The fields an effect names, each declared.
    fn fields_of(&self, key: &str, names: &[String]) -> Result<(bool, bool), SceneError> {
        let (mut s, mut v) = (false, false);
        for f in names {
            let field = match f.as_str() {
                "smoke" => Field::Smoke,
                "velocity" => Field::Velocity,
                other => return Err(SceneError::key(key, unknown("field", other, &["smoke", "velocity"]))),
            };
            if !self.has(field) {
                return Err(SceneError::key(key, format!("needs the field `{f}`, which the scene does not declare (add [fields.{f}])")));
            }
            *(if field == Field::Smoke { &mut s } else { &mut v }) = true;
        }
        if !s && !v {
            return Err(SceneError::key(key, "names no field"));
        }
        Ok((s, v))
    }

    fn need(&self, key: &str, kind: &str, fields: &[Field]) -> Result<(), SceneError> {
        for f in fields {
            if !self.has(*f) {
                return Err(SceneError::key(key, format!("{kind} needs the field `{n}` (add [fields.{n}])", n = f.name())));
            }
        }
        Ok(())
    }

    fn effect(&mut self, k: usize, table: &toml::Table) -> Result<(), SceneError> {
        let at = |key: &str| format!("effects[{k}].{key}");
        let e = super::spec::effect(k, table)?;
        let (domain, dt) = (self.domain, self.dt);
        let line = match domain {
            Domain::Line(l) => Some(l),
            Domain::Box(_) | Domain::Box3(_) => None,
        };
        let box_only = |kind: &str| SceneError::key(at("kind"), format!("{kind} needs a 2D or 3D domain"));
        // Advection, pressure, buoyancy and inflow in a box are built by
        // `box_effect`, once for 2D and 3D; diffusion and forces below for
        // every domain.
        if matches!(e, EffectSpec::Advection(_) | EffectSpec::Pressure(_) | EffectSpec::Buoyancy(_) | EffectSpec::Inflow(_) | EffectSpec::NavierStokes(_)) {
            match domain {
                Domain::Box(cfg) => return self.box_effect(k, e, cfg),
                Domain::Box3(cfg) => return self.box_effect(k, e, cfg),
                Domain::Line(_) => {}
            }
        }
        match (e, domain) {
            (EffectSpec::Advection(a), Domain::Line(l)) => {
                let (s, _) = self.fields_of(&at("fields"), &a.fields)?;
                self.effects.push("advection".into());
                if s {
                    return Err(SceneError::key(at("fields"), "on a line only the velocity is advected (Burgers): fields = [\"velocity\"]"));
                }
                if a.scheme != "upwind" {
                    return Err(SceneError::key(at("scheme"), format!("on a line the advection scheme is \"upwind\", got \"{}\"", a.scheme)));
                }
                if !l.periodic {
                    return Err(SceneError::key(at("kind"), "advection on a line needs boundary = \"periodic\""));
                }
                // Upwind is stable for CFL = max|u|·dt/dx ≤ 1; checked on the initial state.
                let umax = self.x0[domain.range(Field::Velocity)].iter().fold(0.0f64, |m, u| m.max(u.abs()));
                let cfl = umax * dt / l.dx;
                if cfl > 1.0 {
                    return Err(SceneError::key(
                        at("kind"),
                        format!("unstable: the CFL number max|u|·dt/dx = {cfl:.3} of the initial velocity exceeds 1; use dt ≤ {:.4e}", l.dx / umax),
                    ));
                }
                let op = BurgersEnzyme(Burgers1d { n: l.n, dx: l.dx, dt, nu: 0.0 });
                self.ops.push(Box::new(Part::new(op, domain.n_state(), domain.range(Field::Velocity))));
            }
            (EffectSpec::Diffusion(d), _) => {
                let (s, v) = self.fields_of(&at("fields"), &d.fields)?;
                let nu = finite(&at("viscosity"), d.viscosity)?;
                if nu < 0.0 {
                    return Err(SceneError::key(at("viscosity"), format!("must not be negative, got {nu}")));
                }
                // κ = ν·dt/dx² (unit cells in a box).
                let h2 = line.map_or(1.0, |l| l.dx * l.dx);
                let kappa = nu * dt / h2;
                self.effects.push("diffusion".into());
                match d.scheme.as_str() {
                    "explicit" => {
                        // 1/(2·axes): 1/2 on a line, 1/4 in a box, 1/6 in 3D.
                        let limit = 0.5 / domain.dims() as f64;
                        if kappa > limit {
                            return Err(SceneError::key(
                                at("scheme"),
                                format!(
                                    "explicit diffusion is unstable here: viscosity·dt/dx² = {kappa} exceeds the limit {limit}; use dt ≤ {:.4e} or scheme = \"implicit\"",
                                    limit * h2 / nu
                                ),
                            ));
                        }
                        self.ops.push(match (line, domain) {
                            (Some(l), _) => Box::new(Diffuse::line(l.n, l.periodic, s, v, DiffuseExplicit::on)),
                            (None, Domain::Box(cfg)) => Box::new(Diffuse::explicit(cfg, s, v)),
                            (None, Domain::Box3(cfg)) => Box::new(Diffuse::explicit(cfg, s, v)),
                            (None, Domain::Line(_)) => unreachable!("a line has `line`"),
                        });
                    }
                    "implicit" => {
                        let tol = tolerance(&at("tolerance"), d.tolerance)?;
                        let max = iterations(&at("max_iterations"), d.max_iterations, domain.n_state())?;
                        self.ops.push(match (line, domain) {
                            (Some(l), _) => Box::new(Diffuse::line(l.n, l.periodic, s, v, |g| DiffuseImplicit::on(g, tol, max))),
                            (None, Domain::Box(cfg)) => Box::new(Diffuse::implicit(cfg, s, v, tol, max)),
                            (None, Domain::Box3(cfg)) => Box::new(Diffuse::implicit(cfg, s, v, tol, max)),
                            (None, Domain::Line(_)) => unreachable!("a line has `line`"),
                        });
                    }
                    other => return Err(SceneError::key(at("scheme"), unknown("scheme", other, &["explicit", "implicit"]))),
                }
                self.name(k, "diffusion", "viscosity", dt / h2);
                self.params.push(kappa);
            }
            (EffectSpec::Force(f), _) => {
                self.need(&at("kind"), "force", &[Field::Velocity])?;
                if f.value.len() != domain.dims() {
                    return Err(SceneError::key(at("value"), format!("expected {} value(s), one per axis", domain.dims())));
                }
                for (i, a) in f.value.iter().enumerate() {
                    finite(&at(&format!("value[{i}]")), *a)?;
                }
                self.effects.push("force".into());
                let start = self.params.len();
                // The control: the force on every velocity sample, in the velocity's layout.
                let velocity = domain.range(Field::Velocity);
                let arrays: Vec<Array> = domain
                    .arrays(Field::Velocity)
                    .into_iter()
                    .map(|a| Array { range: start + a.range.start - velocity.start..start + a.range.end - velocity.start, ..a })
                    .collect();
                for name in ["force.control".to_string(), at("control")] {
                    if !self.controls.iter().any(|c| c.name == name) {
                        self.controls.push(Control { name, arrays: arrays.clone() });
                    }
                }
                match line {
                    Some(l) => {
                        self.ops.push(Box::new(AddParams { n: domain.n_state(), range: domain.range(Field::Velocity), scale: dt }));
                        self.params.extend(std::iter::repeat_n(f.value[0], l.n));
                    }
                    None => {
                        // One value per face of each axis, in the velocity's layout.
                        let (op, faces): (Box<dyn Effect>, Vec<usize>) = match domain {
                            Domain::Box(cfg) => (Box::new(Force { cfg, dt }), (0..2).map(|a| cfg.n_face(a)).collect()),
                            Domain::Box3(cfg) => (Box::new(Force { cfg, dt }), (0..3).map(|a| cfg.n_face(a)).collect()),
                            Domain::Line(_) => unreachable!("a line has `AddParams`"),
                        };
                        self.ops.push(op);
                        for (&value, count) in f.value.iter().zip(faces) {
                            self.params.extend(std::iter::repeat_n(value, count));
                        }
                    }
                }
            }
            (EffectSpec::Pressure(_) | EffectSpec::Buoyancy(_) | EffectSpec::Inflow(_) | EffectSpec::NavierStokes(_), Domain::Line(_)) => {
                return Err(box_only(table.get("kind").and_then(|v| v.as_str()).unwrap_or("this effect")));
            }
            (_, Domain::Box(_) | Domain::Box3(_)) => unreachable!("built by box_effect"),
        }
        Ok(())
    }

    /// The traced scheme of the `k`-th effect, an advection (`v`: it moves
    /// the velocity), or `None` for upwind (scalars only, by a declared
    /// velocity).
    fn advection_scheme(&self, k: usize, a: &super::spec::AdvectionSpec, v: bool) -> Result<Option<Scheme>, SceneError> {
        let at = |key: &str| format!("effects[{k}].{key}");
        match a.scheme.as_str() {
            "semi_lagrangian" => Ok(Some(Scheme::SemiLagrangian)),
            "maccormack" => Ok(Some(Scheme::MacCormack { limiter: a.limiter })),
            "upwind" if v => {
                Err(SceneError::key(at("scheme"), "upwind advects scalars only; advect the velocity in its own effect with semi_lagrangian or maccormack"))
            }
            "upwind" if !self.has(Field::Velocity) => Err(SceneError::key(at("scheme"), "upwind needs a velocity field (add [fields.velocity])")),
            "upwind" => Ok(None),
            other => Err(SceneError::key(at("scheme"), unknown("scheme", other, &["semi_lagrangian", "maccormack", "upwind"]))),
        }
    }

    /// An effect of a box scene other than diffusion and forces, in 2D and
    /// 3D: advection (semi-Lagrangian, MacCormack, upwind), buoyancy along
    /// any axis, inflow regions and the pressure projection (with
    /// obstacles).
    fn box_effect<const D: usize>(&mut self, k: usize, e: EffectSpec, cfg: MacGrid<D>) -> Result<(), SceneError>
    where
        SmokeAdvect<D>: Effect,
        Advect<D>: Effect,
        AdvectUpwind<D>: Effect,
        Buoyancy<D>: Effect,
        Inflow<D>: Effect,
        Project<D>: Effect,
        NavierStokes<D>: Effect,
    {
        let at = |key: &str| format!("effects[{k}].{key}");
        match e {
            EffectSpec::NavierStokes(ns) => {
                self.need(&at("kind"), "navier_stokes", &[Field::Velocity])?;
                let nu = finite(&at("viscosity"), ns.viscosity)?;
                if nu < 0.0 {
                    return Err(SceneError::key(at("viscosity"), format!("must not be negative, got {nu}")));
                }
                let scheme = match ns.scheme.as_str() {
                    "maccormack" => Scheme::MacCormack { limiter: ns.limiter },
                    "semi_lagrangian" => Scheme::SemiLagrangian,
                    other => return Err(SceneError::key(at("scheme"), unknown("scheme", other, &["maccormack", "semi_lagrangian"]))),
                };
                let tol = tolerance(&at("tolerance"), ns.tolerance)?;
                let max = iterations(&at("max_iterations"), ns.max_iterations, cfg.n_state())?;
                let viscosity = match ns.viscous.as_str() {
                    "explicit" => Viscosity::Explicit,
                    "implicit" => Viscosity::Implicit { tolerance: tol, max_iterations: max },
                    other => return Err(SceneError::key(at("viscous"), unknown("viscous scheme", other, &["explicit", "implicit"]))),
                };
                let precond = preconditioner(&at("preconditioner"), &ns.preconditioner, &["multigrid", "mic0", "none"])?;
                // Unit cells; the domain's sides were validated with the domain.
                let step = NavierStokes::new(cfg, 1.0, scheme).map_err(|e| SceneError::key(at("kind"), e.to_string()))?;
                let mut step = step.with_viscosity(viscosity).with_projection(tol, max, precond);
                if let Some(solid) = self.solid {
                    step = step.with_obstacles(solid).map_err(|e| SceneError::key("obstacles", e.to_string()))?;
                }
                let params = step.params(nu, self.dt);
                self.effects.push("navier_stokes".into());
                self.ops.push(Box::new(Part::new(step, cfg.n_state(), cfg.n_s()..cfg.n_state())));
                self.name(k, "navier_stokes", "viscosity", 1.0);
                self.params.push(params[0]);
                self.name(k, "navier_stokes", "dt", 1.0);
                self.params.extend(&params[1..]);
                self.projected = true;
            }
            EffectSpec::Advection(a) => {
                let (s, v) = self.fields_of(&at("fields"), &a.fields)?;
                self.effects.push("advection".into());
                match self.advection_scheme(k, &a, v)? {
                    // Both fields semi-Lagrangian: P2's and P4's step (in parallel, with its hand adjoint beside it).
                    Some(Scheme::SemiLagrangian) if s && v && cfg.is_closed() => self.ops.push(Box::new(SmokeAdvect(cfg))),
                    Some(scheme) => self.ops.push(Box::new(Advect { cfg, scheme, dt: cfg.dt, smoke: s, velocity: v })),
                    None => self.ops.push(Box::new(AdvectUpwind { cfg, dt: cfg.dt })),
                }
            }
            EffectSpec::Pressure(p) => {
                self.need(&at("kind"), "pressure", &[Field::Velocity])?;
                let tol = tolerance(&at("tolerance"), p.tolerance)?;
                let max = iterations(&at("max_iterations"), p.max_iterations, cfg.n_state())?;
                let precond = preconditioner(&at("preconditioner"), &p.preconditioner, &["multigrid", "mic0", "none"])?;
                self.effects.push("pressure".into());
                self.ops.push(Box::new(match self.solid {
                    Some(s) => Project::with_obstacles(cfg, tol, max, precond, s),
                    None => Project::new(cfg, tol, max, precond),
                }));
                self.projected = true;
            }
            EffectSpec::Buoyancy(b) => {
                if b.field != "smoke" {
                    return Err(SceneError::key(at("field"), unknown("field", &b.field, &["smoke"])));
                }
                let axis = axis_of(&at("axis"), &b.axis)?;
                if axis >= D {
                    return Err(SceneError::key(at("axis"), format!("a {D}D domain has no {} axis", b.axis)));
                }
                self.need(&at("kind"), "buoyancy", &[Field::Smoke, Field::Velocity])?;
                self.effects.push("buoyancy".into());
                self.ops.push(Box::new(Buoyancy { cfg, dt: self.dt, axis }));
                self.name(k, "buoyancy", "coefficient", 1.0);
                self.params.push(finite(&at("coefficient"), b.coefficient)?);
            }
            EffectSpec::Inflow(i) => {
                let (r, values) = inflow(k, &i, &cfg.n, self.dt)?;
                self.effects.push("inflow".into());
                self.ops.push(Box::new(Inflow { cfg, region: std::array::from_fn(|a| [r[2 * a], r[2 * a + 1]]) }));
                self.params.extend(values);
            }
            EffectSpec::Diffusion(_) | EffectSpec::Force(_) => unreachable!("built by `effect` for every domain"),
        }
        Ok(())
    }
}

/// The `k`-th effect, an inflow in a box of `n` cells per axis: its
/// region as half-open cell ranges per axis `[lo₀, hi₀, lo₁, hi₁, …]`
/// (cells whose centre lies inside, clipped to the box) and its parameters
/// `[smoke, velocity…]` (no velocity: at rest). A velocity that crosses
/// the whole box in one step of `dt` is refused: every value would be
/// traced back from outside the box, and the flow it feeds would vanish.
fn inflow(k: usize, i: &super::spec::InflowSpec, n: &[usize], dt: f64) -> Result<(Vec<usize>, Vec<f64>), SceneError> {
    let at = |key: &str| format!("effects[{k}].{key}");
    let dims = n.len();
    let coords = ["x", "y", "z"][..dims].join(", ");
    let ShapeSpec::Box { lower, upper } = &i.region else {
        return Err(SceneError::key(at("region"), "an inflow region must be a box"));
    };
    if lower.len() != dims || upper.len() != dims {
        return Err(SceneError::key(at("region"), format!("expected lower = [{coords}], upper = [{coords}]")));
    }
    let mut region = Vec::with_capacity(2 * dims);
    for a in 0..dims {
        let clip = |v: f64| -> Result<usize, SceneError> { Ok(finite(&at("region"), v)?.clamp(0.0, n[a] as f64).round() as usize) };
        let (lo, hi) = (clip(lower[a])?, clip(upper[a])?);
        if lo >= hi {
            return Err(SceneError::key(at("region"), "the box covers no cell of the domain"));
        }
        region.extend([lo, hi]);
    }
    let mut values = vec![finite(&at("smoke"), i.smoke)?];
    match i.velocity.len() {
        0 => values.extend(vec![0.0; dims]),
        m if m == dims => {
            for (a, &v) in i.velocity.iter().enumerate() {
                values.push(finite(&at(&format!("velocity[{a}]")), v)?);
            }
        }
        m => return Err(SceneError::key(at("velocity"), format!("expected {dims} values, one per axis, got {m}"))),
    }
    // (hypot: the squares of a huge speed would overflow.)
    let speed = values[1..].iter().fold(0.0f64, |a, v| a.hypot(*v));
    let widest = n.iter().copied().max().unwrap_or(0) as f64;
    if speed * dt > widest {
        return Err(SceneError::key(
            at("velocity"),
            format!(
                "moves {:.3e} cells a step (speed × time.dt), more than the box's {widest}: every value would be traced from outside it; lower the speed or the time step",
                speed * dt
            ),
        ));
    }
    Ok((region, values))
}

/// A pressure effect's preconditioner, one of `known`.
fn preconditioner(key: &str, name: &str, known: &[&str]) -> Result<Preconditioner, SceneError> {
    match name {
        "multigrid" if known.contains(&name) => Ok(Preconditioner::Multigrid),
        "mic0" if known.contains(&name) => Ok(Preconditioner::Mic0),
        "none" => Ok(Preconditioner::None),
        other => Err(SceneError::key(key, unknown("preconditioner", other, known))),
    }
}

/// The sides `[lower, upper]` of each of a box's `dims` axes from
/// `domain.boundary`: one kind for every side, or a table of axes (`{ x =
/// …, y = … }`, and `z` in 3D) and sides (`left`, `right`, `bottom`, `top`,
/// and `back`, `front` in 3D), a side overriding its axis; sides named by
/// neither are closed.
fn boundary_sides(v: &toml::Value, dims: usize) -> Result<Vec<[Side; 2]>, SceneError> {
    const KEY: &str = "domain.boundary";
    const AXES: [&str; 3] = ["x", "y", "z"];
    const SIDES: [&str; 6] = ["left", "right", "bottom", "top", "back", "front"];
    let (axes, sides) = (&AXES[..dims], &SIDES[..2 * dims]);
    match v {
        toml::Value::String(_) => {
            let s = side(KEY, v, None)?;
            if matches!(s, Side::Inflow(_)) {
                return Err(SceneError::key(KEY, "inflow must be given per side"));
            }
            Ok(vec![[s, s]; dims])
        }
        toml::Value::Table(t) => {
            for k in t.keys() {
                if !sides.contains(&k.as_str()) && !axes.contains(&k.as_str()) {
                    let known: Vec<&str> = sides.iter().chain(axes).copied().collect();
                    return Err(SceneError::key(format!("{KEY}.{k}"), unknown("side", k, &known)));
                }
            }
            // An axis sets both its sides; a side named overrides its axis.
            // Side 2a + h is the lower (h = 0) or upper side of axis a.
            let one = |k: usize| {
                let mut inward = vec![0.0; dims];
                inward[k / 2] = if k % 2 == 0 { 1.0 } else { -1.0 };
                match (t.get(sides[k]), t.get(axes[k / 2])) {
                    (Some(v), _) => side(&format!("{KEY}.{}", sides[k]), v, Some(&inward)),
                    (None, Some(v)) => side(&format!("{KEY}.{}", axes[k / 2]), v, None),
                    (None, None) => Ok(Side::Closed),
                }
            };
            (0..dims).map(|a| Ok([one(2 * a)?, one(2 * a + 1)?])).collect()
        }
        _ => Err(SceneError::key(
            KEY,
            format!(
                "expected a kind (\"closed\", \"no-slip\", \"periodic\", \"outflow\"), {{ {} = … }} or {{ {} = … }}",
                axes.join(" = …, "),
                sides.join(" = …, ")
            ),
        )),
    }
}

/// One side: a kind, or `{ inflow = [vx, vy(, vz)], profile = "uniform" |
/// "parabolic" }` (`inward`: the side's inward normal, for the inflow
/// speed; its length is the box's dimension).
fn side(key: &str, v: &toml::Value, inward: Option<&[f64]>) -> Result<Side, SceneError> {
    const KINDS: [&str; 6] = ["closed", "free-slip", "no-slip", "periodic", "outflow", "inflow"];
    let coords = |n: usize| ["vx", "vy", "vz"][..n].join(", ");
    match v {
        toml::Value::String(s) => match s.as_str() {
            "closed" | "free-slip" => Ok(Side::Closed),
            "no-slip" => Ok(Side::NoSlip),
            "periodic" => Ok(Side::Periodic),
            "outflow" => Ok(Side::Outflow),
            "inflow" => Err(SceneError::key(key, format!("inflow needs its velocity: {{ inflow = [{}] }}", coords(inward.map_or(2, <[f64]>::len))))),
            other => Err(SceneError::key(key, unknown("boundary kind", other, &KINDS))),
        },
        toml::Value::Table(t) => {
            let Some(normal) = inward else {
                return Err(SceneError::key(key, "inflow is given per side (left, right, bottom, top, and back, front in 3D)"));
            };
            let dims = normal.len();
            for k in t.keys() {
                if k != "inflow" && k != "profile" {
                    return Err(SceneError::key(format!("{key}.{k}"), unknown("key", k, &["inflow", "profile"])));
                }
            }
            let numbers = ["two", "three"][dims - 2];
            let vel: Vec<f64> = t
                .get("inflow")
                .ok_or_else(|| SceneError::key(key, format!("expected {{ inflow = [{}] }}", coords(dims))))?
                .clone()
                .try_into()
                .ok()
                .filter(|v: &Vec<f64>| v.len() == dims)
                .ok_or_else(|| SceneError::key(format!("{key}.inflow"), format!("expected {numbers} numbers [{}]", coords(dims))))?;
            let speed = finite(&format!("{key}.inflow"), vel.iter().zip(normal).map(|(v, n)| v * n).sum())?;
            if speed <= 0.0 {
                return Err(SceneError::key(format!("{key}.inflow"), format!("the velocity {vel:?} does not point into the domain")));
            }
            match t.get("profile").and_then(|p| p.as_str()).unwrap_or("uniform") {
                "uniform" => Ok(Side::Inflow(Profile::Uniform(speed))),
                "parabolic" => Ok(Side::Inflow(Profile::Parabolic(speed))),
                other => Err(SceneError::key(format!("{key}.profile"), unknown("profile", other, &["uniform", "parabolic"]))),
            }
        }
        _ => Err(SceneError::key(key, "expected a kind or { inflow = [...] }")),
    }
}
