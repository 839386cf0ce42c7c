//! The lid-driven cavity against Ghia, Ghia & Shin (1982): the viscous
//! solver ([`diffsim_solvers::flow`]) marched from rest to a steady state,
//! the extrema of the centreline velocities compared with the published
//! table (Re 100, 400 and 1000).

use std::time::Instant;

use diffsim_solvers::flow::cavity::{CavityExtrema, Extremum};
use diffsim_solvers::flow::{Flow2d, SteadyParams, Stepper, cavity_extrema, centrelines, ghia, march_to_steady};

use crate::StudyError;

/// The run's settings; `Default`: Re 100 on 128² cells, steady when
/// `max |du/dt| < 10⁻⁶`, at most 2·10⁶ steps.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CavityParams {
    /// Reynolds number (lid speed × side / ν).
    pub re: f64,
    /// Cells per side.
    pub resolution: usize,
    /// Steady when `max |du/dt|` falls below this.
    pub tolerance: f64,
    /// More time steps than this is an error.
    pub max_steps: usize,
}

impl Default for CavityParams {
    fn default() -> Self {
        CavityParams { re: 100.0, resolution: 128, tolerance: 1e-6, max_steps: 2_000_000 }
    }
}

/// What the run found ([`run`]).
#[derive(Clone, Debug)]
pub struct CavityReport {
    /// The settings.
    pub params: CavityParams,
    /// The flow simulated.
    pub cfg: Flow2d,
    /// The steady velocity (packed `[u, v]`).
    pub state: Vec<f64>,
    /// The centreline extrema.
    pub extrema: CavityExtrema,
    /// Ghia et al.'s, where they tabulate this Reynolds number.
    pub ghia: Option<CavityExtrema>,
    /// Time steps to the steady state.
    pub steps: usize,
    /// Wall seconds.
    pub time_s: f64,
}

/// Marches the cavity from rest to a steady state. `progress(step, time,
/// max |du/dt|)` every 500 steps.
///
/// # Errors
/// A flow that cannot be simulated or does not settle, extrema that are
/// not finite, or a flow that stayed at rest ([`StudyError::NotReported`]).
pub fn run(p: &CavityParams, mut progress: impl FnMut(usize, f64, f64)) -> Result<CavityReport, StudyError> {
    let cfg = Flow2d::cavity(p.resolution, p.re);
    let start = Instant::now();
    let mut stepper = Stepper::new(cfg, 1e-10)?;
    let mut state = cfg.rest();
    let steady = SteadyParams { tolerance: p.tolerance, max_steps: p.max_steps, reference_speed: 1.0 };
    let march = march_to_steady(&mut stepper, &mut state, &steady, |step, t, rate| {
        if step % 500 == 0 {
            progress(step, t, rate);
        }
    })?;
    let extrema = cavity_extrema(&cfg, &state);
    let what = format!("cavity at Re {}", p.re);
    crate::finite_figures(&what, &[("u_min", extrema.u_min.value), ("v_max", extrema.v_max.value), ("v_min", extrema.v_min.value)])?;
    // The lid drives a vortex: a steady state at rest is not the cavity's.
    if diffsim_solvers::cg::max_abs(&state) == 0.0 {
        return Err(StudyError::NotReported { what, reason: "the flow stayed at rest".into() });
    }
    let ghia = ghia(p.re).map(|t| t.extrema());
    Ok(CavityReport { params: *p, cfg, state, extrema, ghia, steps: march.steps, time_s: start.elapsed().as_secs_f64() })
}

impl CavityReport {
    /// `(ours − Ghia's) / Ghia's` of an extremum's value.
    fn relative(ours: Extremum, theirs: Extremum) -> f64 {
        (ours.value - theirs.value) / theirs.value
    }

    /// The one-line result: the extrema with where they are, the grid, the
    /// steps and seconds, and (where tabulated) Ghia's extrema and the
    /// relative errors.
    pub fn json(&self) -> serde_json::Value {
        let e = &self.extrema;
        let ext = |e: &CavityExtrema| {
            serde_json::json!({
                "u_min": e.u_min.value, "y_at_u_min": e.u_min.at,
                "v_max": e.v_max.value, "x_at_v_max": e.v_max.at,
                "v_min": e.v_min.value, "x_at_v_min": e.v_min.at,
            })
        };
        let mut obj = ext(e);
        obj["re"] = self.params.re.into();
        obj["resolution"] = self.params.resolution.into();
        obj["cells"] = (self.cfg.nx * self.cfg.ny).into();
        obj["steps"] = self.steps.into();
        obj["time_s"] = self.time_s.into();
        if let Some(g) = &self.ghia {
            obj["ghia"] = ext(g);
            obj["relative_error"] = serde_json::json!({
                "u_min": Self::relative(e.u_min, g.u_min),
                "v_max": Self::relative(e.v_max, g.v_max),
                "v_min": Self::relative(e.v_min, g.v_min),
            });
        }
        obj
    }

    /// The Markdown table of the extrema against Ghia's (and a line where
    /// Ghia has no table).
    pub fn table(&self) -> String {
        let e = &self.extrema;
        let mut out = String::from("| extremum | diffsim (at) | Ghia et al. 1982 (at) | difference in magnitude |\n|---|---|---|---|\n");
        let rows = [
            ("u_min (x = ½)", e.u_min, self.ghia.map(|g| g.u_min)),
            ("v_max (y = ½)", e.v_max, self.ghia.map(|g| g.v_max)),
            ("v_min (y = ½)", e.v_min, self.ghia.map(|g| g.v_min)),
        ];
        for (name, ours, theirs) in rows {
            match theirs {
                Some(g) => out.push_str(&format!(
                    "| {name} | {:.5} ({:.4}) | {:.5} ({:.4}) | {:+.2} % |\n",
                    ours.value,
                    ours.at,
                    g.value,
                    g.at,
                    100.0 * Self::relative(ours, g)
                )),
                None => out.push_str(&format!("| {name} | {:.5} ({:.4}) | – | – |\n", ours.value, ours.at)),
            }
        }
        if self.ghia.is_none() {
            out.push_str("(Ghia et al. tabulate Re 100, 400 and 1000 only)\n");
        }
        out
    }

    /// The centreline profiles: `(position, u)` on `x = ½` and `(position,
    /// v)` on `y = ½`.
    pub fn profiles(&self) -> [Vec<(f64, f64)>; 2] {
        let (ul, vl) = centrelines(&self.cfg, &self.state);
        [ul.at.iter().copied().zip(ul.value.iter().copied()).collect(), vl.at.iter().copied().zip(vl.value.iter().copied()).collect()]
    }

    /// The profiles as CSV, `line,position,velocity`.
    pub fn profiles_csv(&self) -> String {
        let [u, v] = self.profiles();
        let mut csv = String::from("line,position,velocity\n");
        for (at, val) in u {
            csv.push_str(&format!("u(x=0.5),{at:.6},{val:.8}\n"));
        }
        for (at, val) in v {
            csv.push_str(&format!("v(y=0.5),{at:.6},{val:.8}\n"));
        }
        csv
    }
}
