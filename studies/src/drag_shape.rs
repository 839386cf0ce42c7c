//! The minimum-drag shape at fixed area: a Fourier-boundary body in the
//! Schäfer–Turek channel or in a free stream, its drag minimised by L-BFGS
//! through the steady solver's adjoint (then gradient sampling where the
//! discrete drag's kinks stall the line search), and the reduction against
//! the cylinder re-simulated on a grid twice as fine (docs/drag-shape.md).

use std::time::Instant;

use diffsim_solvers::flow::drag_shape::{DragShapeParams, DragShapeResult, Stream, drag_coefficient, optimise_from};

use crate::StudyError;

/// The study's settings: the optimisation's ([`DragShapeParams`]; its
/// `Default` the channel at Re 20, 20 cells per diameter, modes 2..=8), the
/// start and the verification.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct DragStudyParams {
    /// The optimisation.
    pub optimise: DragShapeParams,
    /// The start's free Fourier coefficients (`a₂…a_K, b₂…b_K`); `None`
    /// starts from the cylinder.
    pub start: Option<Vec<f64>>,
    /// Re-simulate the cylinder and the optimum on a grid twice as fine.
    pub verify: bool,
}

impl DragStudyParams {
    /// Where the body sits, in words.
    pub fn place(&self) -> String {
        match self.optimise.stream {
            Stream::Channel => "the channel".to_string(),
            Stream::Free { half_width } => format!("a free stream ({half_width} diameters to each side)"),
        }
    }

    /// The Reynolds number without the rounding noise of `u_max`'s round trip.
    pub fn reynolds_shown(&self) -> f64 {
        (self.optimise.reynolds() * 1e6).round() / 1e6
    }
}

/// What [`run`] found.
#[derive(Clone, Debug)]
pub struct DragShapeReport {
    /// The settings.
    pub params: DragStudyParams,
    /// The optimisation's result.
    pub result: DragShapeResult,
    /// The cylinder's drag coefficient on the optimisation's grid (the
    /// reduction is against it, whatever the start).
    pub cd_cylinder: f64,
    /// With `verify`: the cylinder's and the optimum's drag coefficients on
    /// the grid twice as fine.
    pub fine: Option<(f64, f64)>,
    /// Seconds of the optimisation.
    pub optimise_s: f64,
    /// Seconds in all (with the verification).
    pub time_s: f64,
}

/// Minimises the drag, then (with `verify`) re-simulates both shapes on a
/// grid twice as fine.
///
/// # Errors
/// A flow that cannot be solved, or a figure that is not finite
/// ([`StudyError::NotReported`]).
pub fn run(p: &DragStudyParams) -> Result<DragShapeReport, StudyError> {
    let o = &p.optimise;
    let start = Instant::now();
    let setting = o.stream.setting(o.cells_per_d, o.u_max)?;
    let q0 = p.start.clone().unwrap_or_else(|| vec![0.0; 2 * o.modes.saturating_sub(1)]);
    let result = optimise_from(o, &q0)?;
    let cd_cylinder = if p.start.is_some() { drag_coefficient(&setting, &setting.cylinder)? } else { result.cd_start };
    let optimise_s = start.elapsed().as_secs_f64();
    let fine = if p.verify {
        let fine = o.stream.setting(2 * o.cells_per_d, o.u_max)?;
        Some((drag_coefficient(&fine, &fine.cylinder)?, drag_coefficient(&fine, &result.shape)?))
    } else {
        None
    };
    let report = DragShapeReport { params: p.clone(), result, cd_cylinder, fine, optimise_s, time_s: start.elapsed().as_secs_f64() };
    let mut figures = vec![
        ("c_D of the cylinder", report.cd_cylinder),
        ("c_D of the optimum", report.result.cd_end),
        ("the reduction", report.reduction()),
        ("the area", report.result.area_end),
    ];
    if let (Some((s, e)), Some(f)) = (report.fine, report.fine_reduction()) {
        figures.extend([("c_D of the cylinder re-simulated", s), ("c_D of the optimum re-simulated", e), ("the re-simulated reduction", f)]);
    }
    crate::finite_figures("drag-shape", &figures)?;
    Ok(report)
}

impl DragShapeReport {
    /// The drag's reduction against the cylinder, in percent.
    pub fn reduction(&self) -> f64 {
        100.0 * (1.0 - self.result.cd_end / self.cd_cylinder)
    }

    /// The reduction re-simulated on the finer grid, in percent.
    pub fn fine_reduction(&self) -> Option<f64> {
        self.fine.map(|(start, end)| 100.0 * (1.0 - end / start))
    }

    /// How many times the projected gradient shrank.
    pub fn shrink(&self) -> f64 {
        self.result.gradient_start / self.result.gradient_end
    }

    /// The one-line result (the keys `drag-shape --json` prints).
    pub fn json(&self) -> serde_json::Value {
        let (o, r, per_d) = (&self.params.optimise, &self.result, self.params.optimise.cells_per_d);
        let fine = self.fine;
        serde_json::json!({
            "re": o.reynolds(), "resolution": per_d, "modes": o.modes,
            "stream": match o.stream { Stream::Channel => "channel", Stream::Free { .. } => "free" },
            "half_width": match o.stream { Stream::Channel => None, Stream::Free { half_width } => Some(half_width) },
            "cd_start": r.cd_start, "cd_end": r.cd_end, "cd_cylinder": self.cd_cylinder, "area_start": r.area_start, "area_end": r.area_end,
            "iterations": r.iterations, "solves": r.solves, "time_s": self.time_s, "optimise_s": self.optimise_s,
            "gradient_start": r.gradient_start, "gradient_end": r.gradient_end, "gradient_shrink": self.shrink(),
            "fine_resolution": fine.map(|_| 2 * per_d), "cd_start_fine": fine.map(|f| f.0), "cd_end_fine": fine.map(|f| f.1),
            "reduction_pct": self.reduction(), "reduction_fine_pct": self.fine_reduction(),
            "shape": {"r0": match &r.shape { diffsim_solvers::flow::Shape::Fourier { r0, .. } => *r0, _ => f64::NAN }, "params": r.shape.params()},
            "stopped": r.stopped,
            "sampling": r.sampling.map(|s| serde_json::json!({
                "iterations": s.iterations, "steps": s.steps, "min_norm": s.min_norm, "radius": s.radius, "converged": s.converged,
                "shrink": r.gradient_start / s.min_norm,
            })),
        })
    }

    /// The heading, the table against the cylinder and what the stopping
    /// means; `start` names where an earlier shape came from (a file).
    pub fn table(&self, start: Option<&str>) -> String {
        let (o, r, per_d) = (&self.params.optimise, &self.result, self.params.optimise.cells_per_d);
        let (reduction, shrink) = (self.reduction(), self.shrink());
        let mut out = format!(
            "Minimum drag at fixed area in {}, Re {}, {per_d} cells per diameter, Fourier modes 2..={}: {} L-BFGS iterations, {} steady solves, {:.1} s\n",
            self.params.place(),
            self.params.reynolds_shown(),
            o.modes,
            r.iterations,
            r.solves,
            self.optimise_s
        );
        if let Some(why) = &r.stopped {
            out.push_str(&format!("(L-BFGS stopped early: {why})\n"));
        }
        if let Some(from) = start {
            out.push_str(&format!("(started from {from}: c_D {:.4}; the gradient below shrinks from that start's)\n", r.cd_start));
        }
        out.push_str("| | cylinder | optimised | reduction |\n|---|---|---|---|\n");
        out.push_str(&format!("| c_D ({per_d} per D) | {:.4} | {:.4} | {reduction:.2} % |\n", self.cd_cylinder, r.cd_end));
        if let (Some((fine_start, fine_end)), Some(fine_reduction)) = (self.fine, self.fine_reduction()) {
            out.push_str(&format!("| c_D ({} per D, re-simulated) | {fine_start:.4} | {fine_end:.4} | {fine_reduction:.2} % |\n", 2 * per_d));
        }
        out.push_str(&format!("| area | {:.6e} | {:.6e} | {:+.2e} % |\n", r.area_start, r.area_end, 100.0 * (r.area_end / r.area_start - 1.0)));
        out.push_str(&format!("| projected gradient | {:.3e} | {:.3e} | shrunk {shrink:.0}× |\n", r.gradient_start, r.gradient_end));
        match r.sampling {
            Some(s) => {
                let sampled = r.gradient_start / s.min_norm;
                out.push_str(&format!("| smallest gradient sampled within {:.2e} of the final shape | | {:.3e} | shrunk {sampled:.0}× |\n", s.radius, s.min_norm));
                out.push_str(&format!(
                    "(L-BFGS stopped short of 100× at a kink of the discrete drag, where the gradient jumps; {} iterations of gradient sampling followed, {} steps taken{})\n",
                    s.iterations,
                    s.steps,
                    if s.converged { ": the final shape is stationary to 100× among its neighbours' gradients" } else { ": not stationary to 100× even so" }
                ));
            }
            None if shrink < 100.0 => out.push_str(
                "The projected gradient shrank less than 100×: the line search stalled at a kink of the discrete drag (a grid node crossing the boundary); the optimum is not verified to that standard.\n",
            ),
            None => {}
        }
        out
    }
}
