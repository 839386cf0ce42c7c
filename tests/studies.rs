//! The studies through their reports (`diffsim_studies::{heat,
//! oscillators}::run`), not through the program: what each found, its
//! table, CSV and one-line result, and a resumed run reading its finished
//! parts back. The command line's own tests (`cli.rs`) keep the arguments,
//! messages and files.

use diffsim::train::checkpoint::Parts;

fn temp(name: &str) -> std::path::PathBuf {
    std::env::temp_dir().join(format!("diffsim-study-{name}-{}", std::process::id()))
}

#[test]
fn sip_heat_report_ranks_sip_above_adam_and_reads_back_its_parts() {
    use diffsim_studies::heat::{HeatParams, Method, run};
    let cfg = HeatParams { iterations: 40, batch: 4, test_samples: 6, ..HeatParams::standard() };
    let mut calls = 0;
    let report = run(&cfg, None, |_, _| calls += 1).unwrap();
    assert_eq!(calls, 3 * cfg.iterations);
    let names: Vec<&str> = report.curves.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, Method::ALL.map(Method::name));
    // The same start (the same network and test set), then SIP ahead of
    // Adam and gradient descent (Holl et al. 2022, fig. 3; the first
    // updates from the zero-output start raise every error a little, SIP's
    // least: start 299.2, SIP 303.0, Adam 315.8, GD 326.1 here).
    let start = report.curves[0].points[0].1;
    assert!(report.curves.iter().all(|c| c.points[0].1 == start && c.updates == cfg.iterations));
    let (sip, adam, gd) = (report.curves[0].final_loss(), report.curves[1].final_loss(), report.curves[2].final_loss());
    assert!(sip < adam && sip < gd && sip < 1.05 * start, "start {start}, SIP {sip}, Adam {adam}, GD {gd}");
    assert!(report.inverse_l1 > 0.0 && report.inverse_l2.is_finite());
    // The files' contents: a row per optimizer and the inverse's, a CSV row per point, the JSON keys.
    let table = report.table();
    assert_eq!(table.lines().count(), 2 + 3 + 1, "{table}");
    assert!(table.contains("| sip | 40 |") && table.contains("the inverse alone"));
    let points: usize = report.curves.iter().map(|c| c.points.len()).sum();
    assert_eq!(report.csv().lines().count(), 1 + points);
    let json = report.json();
    for key in ["sip", "adam", "gd", "sip_s", "adam_s", "gd_s", "sip_x_l2", "adam_x_l2", "gd_x_l2", "inverse", "inverse_x_l2"] {
        assert!(json[key].as_f64().is_some_and(f64::is_finite), "{key}");
    }
    assert_eq!(json["sip"].as_f64(), Some(sip));
    // With parts: the first run saves each optimizer's curve; a resumed
    // run reads them back instead of training (no progress calls).
    let dir = temp("heat");
    let small = HeatParams { iterations: 3, ..cfg };
    let first = run(&small, Some(&Parts::open(&dir, "test".into(), false).unwrap()), |_, _| {}).unwrap();
    let mut again = 0;
    let resumed = run(&small, Some(&Parts::open(&dir, "test".into(), true).unwrap()), |_, _| again += 1).unwrap();
    assert_eq!(again, 0);
    assert_eq!(serde_json::to_string(&first).unwrap(), serde_json::to_string(&resumed).unwrap());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn sip_heat_published_setup_runs_end_to_end() {
    // The published setup, scaled down: the 4-level float32 U-Net with the
    // mean correction and the Bayesian inverse.
    use diffsim_studies::heat::{HeatParams, run};
    let cfg = HeatParams { batch: 2, test_samples: 2, ..HeatParams::published(2) };
    let report = run(&cfg, None, |_, _| {}).unwrap();
    for c in &report.curves {
        assert!(c.final_loss() > 0.0 && c.final_loss().is_finite(), "{}: {:?}", c.name, c.points);
        assert!(c.second_points.last().is_some_and(|p| p.1 > 0.0 && p.1.is_finite()), "{}", c.name);
    }
}

#[test]
fn hig_report_puts_hig_ahead_of_adam_per_update_on_the_linear_problem() {
    use diffsim::distributed::World;
    use diffsim_studies::oscillators::{OscMethod, OscParams, run};
    let quick = |c: OscParams| OscParams { updates: Some(12), test_samples: 256, ..c };
    let (linear, nonlinear) = (quick(OscParams::linear(0.0)), OscParams { updates: Some(2), ..quick(OscParams::nonlinear(0.0)) });
    let report = run(&linear, &nonlinear, &World::single(), None, |_, _, _| {}).unwrap();
    let names: Vec<&str> = report.linear.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, OscMethod::ALL.map(OscMethod::name));
    assert!(report.linear.iter().all(|c| c.updates == 12) && report.nonlinear.iter().all(|c| c.updates == 2 || c.diverged_after.is_some()));
    // Same start; twelve HIG updates lower the linear problem's test loss
    // far more than twelve of Adam's (Schnell et al. 2022, fig. 2; 0.057
    // against 0.41 here).
    let (hig, adam) = (&report.linear[0], &report.linear[1]);
    assert_eq!(hig.points[0].1, adam.points[0].1);
    assert!(hig.final_loss() < 0.25 * adam.final_loss(), "HIG {} vs Adam {}", hig.final_loss(), adam.final_loss());
    let table = report.table();
    assert_eq!(table.lines().count(), 2 + 6, "{table}");
    let json = report.json();
    for key in ["hig", "adam", "gn", "hig_nonlinear", "adam_nonlinear_s_per_update", "gn_updates", "hig_diverged"] {
        assert!(json.contains_key(key), "{key}");
    }
    assert_eq!(json["hig_updates"].as_u64(), Some(12));
    let points: usize = report.linear.iter().chain(&report.nonlinear).map(|c| c.points.len()).sum();
    assert_eq!(report.csv().lines().count(), 1 + points);
}

#[test]
fn the_quick_burgers_study_puts_sol16_below_pre_and_the_source() {
    use diffsim::distributed::World;
    use diffsim_studies::burgers::{StudyParams, study};
    use diffsim_studies::sol::SolReport;
    let cfg = StudyParams::standard(true);
    let mut rows = 0;
    let report = SolReport::new(&cfg, study(&cfg, None, &World::single(), |_, _| rows += 1).unwrap());
    assert_eq!(rows, cfg.methods.len() * cfg.settings.iterations);
    let e = |name: &str| report.variant(name).unwrap_or_else(|| panic!("{name}")).mean_error;
    // Um et al. 2020: the unrolled training corrects the coarse solver most.
    assert!(e("sol16") < e("pre") && e("sol16") < e("source") / 3.0, "sol16 {}, pre {}, source {}", e("sol16"), e("pre"), e("source"));
    let table = report.table();
    assert_eq!(table.lines().count(), 2 + report.variants.len(), "{table}");
    assert_eq!(report.csv().lines().count(), 1 + cfg.eval_steps);
    let json = report.json();
    assert_eq!(json["sol16"].as_f64(), Some(e("sol16")));
    assert_eq!(json["iterations"].as_u64(), Some(cfg.settings.iterations as u64));
    assert!(json["train_set"]["source"].as_f64().is_some());
}

#[test]
fn sip_smoke_report_measures_the_inverses_promise() {
    use diffsim_studies::smoke::{SHOWN, SmokeParams, run};
    let cfg = SmokeParams { seconds: 0.5, ..SmokeParams::quick() };
    let report = run(&cfg, 2, |_, _| {}).unwrap();
    assert_eq!(report.runs.iter().map(|r| r.curve.name.as_str()).collect::<Vec<_>>(), ["sip", "adam"]);
    for r in &report.runs {
        assert!(r.curve.updates >= 1 && r.curve.final_loss() > 0.0 && r.curve.final_loss().is_finite(), "{}", r.curve.name);
        assert_eq!(r.shown.len(), report.truth.len());
    }
    assert!(report.truth.len() == SHOWN.min(report.truth.len()) && report.observed.len() == report.truth.len());
    // The inverse's promise is measured at three scales; for small changes
    // it beats "nothing moved" (for a change as large as replacing one
    // state by another it need not: docs/sip.md).
    assert_eq!(report.misses.iter().map(|m| m.scale).collect::<Vec<_>>(), [1.0, 0.1, 0.01]);
    assert!(report.misses.iter().all(|m| m.reverse_time > 0.0 && m.reverse_time.is_finite()));
    let small = report.misses[2];
    assert!(small.reverse_time < small.unmoved, "{small:?}");
    assert!(report.inverse.0 > 0.0 && report.inverse.1.is_finite());
    let table = report.table();
    assert_eq!(table.lines().count(), 2 + 2 + 1 + 3 + 2 + 3, "{table}");
    let json = report.json();
    for key in ["sip", "adam", "time_s", "sip_resim", "adam_resim", "sip_s_per_update", "adam_s_per_update", "inverse", "inverse_resim"] {
        assert!(json[key].as_f64().is_some_and(|v| v.is_finite() && v > 0.0), "{key}");
    }
    let points: usize = report.runs.iter().map(|r| r.curve.points.len()).sum();
    assert_eq!(report.csv().lines().count(), 1 + points);
}

#[test]
fn the_cavity_report_compares_with_ghia() {
    use diffsim_studies::cavity::{CavityParams, run};
    let p = CavityParams { resolution: 16, ..CavityParams::default() };
    let report = run(&p, |_, _, _| {}).unwrap();
    // 16² is coarse: within 10 % of Ghia et al. (u_min −0.2109 at Re 100).
    assert!((report.extrema.u_min.value + 0.2109).abs() < 0.021, "{:?}", report.extrema);
    let g = report.ghia.expect("Ghia tabulates Re 100");
    assert_eq!(g.v_max.value, 0.17527);
    assert!(report.steps > 10 && report.time_s > 0.0);
    let json = report.json();
    assert_eq!(json["cells"].as_u64(), Some(256));
    let rel = (report.extrema.u_min.value - g.u_min.value) / g.u_min.value;
    assert_eq!(json["relative_error"]["u_min"].as_f64(), Some(rel));
    assert_eq!(report.table().lines().count(), 2 + 3);
    let [u, v] = report.profiles();
    assert_eq!(report.profiles_csv().lines().count(), 1 + u.len() + v.len());
    // Without Ghia's table the report says so.
    let no_table = run(&CavityParams { re: 50.0, resolution: 8, ..CavityParams::default() }, |_, _, _| {}).unwrap();
    assert!(no_table.ghia.is_none() && no_table.table().contains("tabulate Re 100, 400 and 1000 only"));
}

#[test]
fn the_cylinder_reports_compare_with_schafer_turek() {
    use diffsim_solvers::flow::Convection;
    use diffsim_studies::cylinder::{CylinderCase, CylinderParams, CylinderResult, SteadySolver, run, sweep};
    let steady = |solver, convection| {
        let p = CylinderParams { resolution: 10, solver, convection, ..CylinderParams::steady() };
        let report = run(&p, |_| {}).unwrap();
        let CylinderResult::Steady(r) = report.result else { panic!("2D-1 reports a steady result") };
        (report, r)
    };
    let (newton_report, newton) = steady(SteadySolver::Newton, Convection::Second);
    assert_eq!(newton.cells, 220 * 41);
    assert!((newton.cd - 5.5795).abs() < 0.03 * 5.5795, "{newton:?}");
    let json = newton_report.json();
    assert_eq!((json["case"].as_str(), json["solver"].as_str(), json["convection"].as_str()), (Some("2d-1"), Some("newton"), Some("second")));
    assert_eq!(json["cd"].as_f64(), Some(newton.cd));
    assert!(newton_report.table().contains("| c_D |") && newton_report.series_csv().is_none());
    // Pseudo-time marching reaches the same discrete steady state as Newton.
    let (_, march) = steady(SteadySolver::March, Convection::Second);
    assert!((march.cd - newton.cd).abs() < 1e-4, "{march:?} against {newton:?}");
    // The same with the fourth-order interpolation: Newton's Jacobian (a
    // wider colouring) converges in a few steps to the march's state.
    let (_, newton4) = steady(SteadySolver::Newton, Convection::Fourth);
    let (_, march4) = steady(SteadySolver::March, Convection::Fourth);
    assert!(newton4.steps <= 8, "{newton4:?}");
    assert!((march4.cd - newton4.cd).abs() < 1e-4, "{march4:?} against {newton4:?}");
    assert!((newton4.cd - newton.cd).abs() > 1e-3, "the scheme changes the flow: {newton4:?}");
    // 2D-2 at 10 cells per diameter with the default fourth-order
    // interpolation: the period within 5 %, the lift peak within 5 %, the
    // drag peak within 7 % (it converges from above), Δp from below (2.20
    // against 2.46–2.50).
    let p = CylinderParams { resolution: 10, t_end: 8.0, ..CylinderParams::periodic() };
    assert_eq!(p.case, CylinderCase::Periodic);
    let report = run(&p, |_| {}).unwrap();
    let CylinderResult::Periodic(r) = &report.result else { panic!("2D-2 reports a periodic result") };
    assert!(r.cl_min < r.cl_mean && r.cl_mean < r.cl_max, "{r:?}");
    assert!((r.dp - 2.48).abs() < 0.12 * 2.48, "{r:?}");
    assert!((r.st - 0.3).abs() < 0.015 && (r.cl_max - 1.0).abs() < 0.05 && (r.cd_max - 3.23).abs() < 0.22, "{r:?}");
    assert_eq!(report.json()["convection"].as_str(), Some("fourth"));
    assert_eq!(report.series_csv().unwrap().lines().count(), 1 + r.series.len());
    // The error-against-time sweep: the drag's error falls with the resolution.
    let s = sweep(&[10, 20], Convection::Second).unwrap();
    assert_eq!(s.rows.len(), 2);
    assert!(s.rows[1].cd_error() < 0.5 * s.rows[0].cd_error(), "{:?}", s.rows);
    assert_eq!(s.rows[0].result, newton, "the sweep's first row is the Newton run at 10");
    assert_eq!(s.json()["sweep"][1]["cd_error"].as_f64(), Some(s.rows[1].cd_error()));
    assert_eq!(s.table().lines().count(), 3 + 2);
}

/// The shape optimisation, reduced (modes up to 4, 8 iterations, 10 cells
/// per diameter): the drag falls, the area holds, the reduction survives a
/// grid twice as fine; continued from its final shape, the start is that
/// shape and the reduction still counts from the cylinder.
#[test]
fn the_drag_shape_report_lowers_the_drag_at_fixed_area() {
    use diffsim_solvers::flow::drag_shape::DragShapeParams;
    use diffsim_studies::drag_shape::{DragStudyParams, run};
    let optimise = DragShapeParams { cells_per_d: 10, modes: 4, max_iterations: 8, sampling_iterations: 1, ..DragShapeParams::default() };
    let report = run(&DragStudyParams { optimise, start: None, verify: true }).unwrap();
    let r = &report.result;
    assert!((1..=8).contains(&r.iterations), "{} iterations", r.iterations);
    assert!(r.cd_end < 0.9 * r.cd_start && report.cd_cylinder == r.cd_start, "{} from {}", r.cd_end, r.cd_start);
    assert!((r.area_end / r.area_start - 1.0).abs() < 1e-12);
    let fine = report.fine_reduction().expect("verified");
    assert!((report.reduction() - fine).abs() < 2.0, "{} against {fine} on the finer grid", report.reduction());
    // Gradient sampling follows when 8 L-BFGS steps leave the gradient
    // above a hundredth of the start's, else it does not run.
    match r.sampling {
        Some(s) => assert!(report.shrink() < 100.0 && s.iterations == 1 && s.min_norm > 0.0 && s.radius > 0.0, "{s:?}"),
        None => assert!(report.shrink() >= 100.0),
    }
    let json = report.json();
    assert_eq!(json["reduction_pct"].as_f64(), Some(report.reduction()));
    assert_eq!(json["cd_end_fine"].as_f64(), report.fine.map(|f| f.1));
    assert!(report.table(None).contains("| c_D (20 per D, re-simulated) |"));
    // Continue from the final shape: its free coefficients a₂…a₄, b₂…b₄.
    let q = r.shape.params();
    let k = (q.len() - 3) / 2;
    let start: Vec<f64> = q[4..3 + k].iter().chain(&q[4 + k..]).copied().collect();
    let optimise = DragShapeParams { max_iterations: 0, sampling_iterations: 0, ..optimise };
    let again = run(&DragStudyParams { optimise, start: Some(start), verify: false }).unwrap();
    assert!((again.result.cd_start - r.cd_end).abs() < 1e-8 * r.cd_end, "{} after {}", again.result.cd_start, r.cd_end);
    assert!((again.cd_cylinder - r.cd_start).abs() < 1e-8 * r.cd_start);
    assert!((again.reduction() - report.reduction()).abs() < 1e-6);
    assert!(again.fine.is_none() && again.table(Some("end.json")).contains("(started from end.json:"));
}

/// `diffsim pareto`'s gradient and cylinder sweeps through their reports:
/// the adjoints agree to round-off and the best finite difference to its
/// truncation/round-off balance; c_D's error falls with the resolution and
/// both steady solvers reach the same discrete state.
#[test]
fn the_pareto_reports_measure_gradients_and_the_cylinder() {
    use diffsim_studies::accuracy::pareto::{ParetoParams, ParetoProblem, run};
    let report = run(&ParetoParams { problem: ParetoProblem::TaylorGreenGradients, quick: true, budget: 0.0 }).unwrap();
    assert!(report.warnings.is_empty(), "{:?}", report.warnings);
    let method = |r: &diffsim_studies::accuracy::pareto::Measurement| r.params["method"].as_str().unwrap_or("").to_string();
    let adjoint: Vec<_> = report.rows.iter().filter(|r| method(r) != "finite differences").collect();
    assert!(adjoint.len() == 6 && adjoint.iter().all(|r| r.error < 1e-8), "{:?}", report.rows);
    let best_fd = report.rows.iter().filter(|r| method(r) == "finite differences").map(|r| r.error).fold(f64::INFINITY, f64::min);
    assert!(best_fd < 1e-4, "best finite difference error {best_fd}");
    assert!(report.rows.iter().any(|r| r.pareto));
    assert_eq!(report.csv().lines().count(), 1 + report.rows.len());
    assert_eq!(report.markdown().lines().count(), 2 + report.rows.len());
    assert_eq!(report.json().as_array().map(Vec::len), Some(report.rows.len()));
    let report = run(&ParetoParams { problem: ParetoProblem::Cylinder, quick: true, budget: 0.0 }).unwrap();
    let error =
        |solver: &str, n: u64| report.rows.iter().find(|r| r.params["solver"] == solver && r.params["cells_per_d"] == n).map(|r| r.error).expect("the row");
    assert!(error("newton", 20) < error("newton", 10) && error("newton", 20) < 0.005, "{:?}", report.rows);
    assert!((error("march", 10) - error("newton", 10)).abs() < 1e-4, "{:?}", report.rows);
    let (families, front) = report.series();
    assert_eq!(families.len(), 2);
    assert!(!front.is_empty() && front.windows(2).all(|w| w[0].0 <= w[1].0));
}
