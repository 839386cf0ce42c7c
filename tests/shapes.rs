//! Differentiable shapes in a flow (`diffsim_solvers::flow::{Shape, Cut,
//! SteadyFlow}`, `diffsim::problems::drag`): the level set's hand-written
//! derivatives against Enzyme's, the cut and the steady force through the
//! three gradient checks, and malformed shapes refused.

use diffsim::check::{CheckParams, check_all};
use diffsim::op::{Forward, OpError, OperatorExt};
use diffsim::problems::drag::{CutOperator, FourierLevel, SteadyForce};
use diffsim_solvers::boundary::{Boundary, Profile, Side};
use diffsim_solvers::flow::{Convection, Flow2d, FlowError, Shape, ShapeError, SteadyFlow, WallSpeed};

/// A short channel (0.5 × 0.41, 10 cells per 0.1) with the Schäfer–Turek
/// inflow of peak 0.3 and ν = 10⁻³: Re 20 around a body of size 0.1.
fn short_channel() -> Flow2d {
    Flow2d {
        nx: 50,
        ny: 41,
        h: 0.01,
        nu: 1e-3,
        boundary: Boundary { sides: [[Side::Inflow(Profile::Parabolic(0.3)), Side::Outflow], [Side::Closed, Side::Closed]] },
        wall_speed: WallSpeed::default(),
        convection: Convection::default(),
    }
}

/// A Fourier body off the grid's symmetries (no node on its boundary).
fn fourier() -> Shape {
    Shape::Fourier { center: [0.2013, 0.2007], r0: 0.0503, cos: vec![0.004, -0.003], sin: vec![0.002, 0.0015] }
}

#[test]
fn the_level_set_derivatives_match_enzyme() {
    let shape = fourier();
    let p = shape.params();
    let points: Vec<f64> = (0..40)
        .flat_map(|k| {
            let a = 0.37 * k as f64;
            [0.2 + (0.03 + 0.001 * k as f64) * a.cos(), 0.2 + (0.04 + 0.0005 * k as f64) * a.sin()]
        })
        .collect();
    let op = FourierLevel { n_points: 40, modes: 2 };
    for k in 0..40 {
        let mut seed = vec![0.0; 40];
        seed[k] = 1.0;
        let (dx, dp) = op.vjp_new(&points, &p, &seed);
        let mut hand = vec![0.0; p.len()];
        let (phi, g) = shape.level_grad(points[2 * k], points[2 * k + 1], &mut hand);
        assert!((phi - shape.level(points[2 * k], points[2 * k + 1])).abs() < 1e-15);
        for (a, b) in hand.iter().zip(&dp) {
            assert!((a - b).abs() < 1e-12, "point {k}: ∂φ/∂p {hand:?} (hand) against {dp:?} (Enzyme)");
        }
        assert!((g[0] - dx[2 * k]).abs() < 1e-12 && (g[1] - dx[2 * k + 1]).abs() < 1e-12, "point {k}: ∇φ {g:?} against {:?}", &dx[2 * k..2 * k + 2]);
    }
}

#[test]
fn the_cut_of_a_fourier_body_and_a_polygon_passes_the_three_checks() {
    let cfg = Flow2d { nx: 30, ny: 28, h: 0.01, ..short_channel() };
    let polygon = Shape::Polygon { vertices: vec![[0.1013, 0.1507], [0.1817, 0.1003], [0.2209, 0.1611], [0.1421, 0.2012]] };
    let opts = CheckParams { tol: 1e-5, ..Default::default() };
    for shape in [fourier(), polygon] {
        shape.validate(&cfg).unwrap();
        let op = CutOperator::new(cfg, shape.clone());
        let report = check_all(&op, &shape.params(), &[], &opts);
        assert!(report.passed(), "{shape:?}\n{report}");
    }
}

/// The end-to-end gradient of the steady drag and lift with respect to a
/// Fourier body's parameters (adjoint of the converged Newton system)
/// against central differences of whole Newton solves; the adjoint against
/// the tangent equations (dot product); the Taylor remainder.
#[test]
fn the_steady_force_gradient_passes_the_three_checks() {
    let cfg = short_channel();
    let start = diffsim_solvers::flow::cylinder::poiseuille(&cfg, 0.3);
    let op = SteadyForce::new(cfg, vec![fourier()], start, [10, 30, 10, 30]).unwrap();
    let opts = CheckParams { tol: 1e-5, max_indices: 7, ..Default::default() };
    let report = check_all(&op, &fourier().params(), &[], &opts);
    assert!(report.passed(), "{report}");
    // The drag changes with every kind of parameter.
    let (g, _) = op.vjp_new(&fourier().params(), &[], &[1.0, 0.0]);
    assert!(g.iter().all(|v| v.abs() > 1e-6), "drag gradient {g:?}");
}

#[test]
fn malformed_shapes_are_refused_with_what_is_wrong() {
    let cfg = short_channel();
    let negative = Shape::Fourier { center: [0.2, 0.2], r0: 0.02, cos: vec![0.03], sin: vec![] };
    assert!(matches!(negative.validate(&cfg), Err(ShapeError::Radius { .. })));
    let bow_tie = Shape::Polygon { vertices: vec![[0.1, 0.1], [0.2, 0.2], [0.2, 0.1], [0.1, 0.2]] };
    assert!(matches!(bow_tie.validate(&cfg), Err(ShapeError::SelfIntersecting { .. })));
    let outside = Shape::Circle { center: [0.2, 0.39], radius: 0.05 };
    let e = outside.validate(&cfg).unwrap_err();
    assert!(matches!(e, ShapeError::LeavesDomain { .. }) && e.to_string().contains("within a cell"), "{e}");
    assert!(matches!(Shape::Polygon { vertices: vec![[0.1, 0.1], [0.2, 0.2]] }.validate(&cfg), Err(ShapeError::TooFewVertices(2))));
    assert!(matches!(fourier().with_params(&[1.0]), Err(ShapeError::Parameters { expected: 7, given: 1 })));
    let nan = Shape::Circle { center: [f64::NAN, 0.2], radius: 0.05 };
    assert!(matches!(nan.validate(&cfg), Err(ShapeError::NotFinite)));
    // The steady solver and the force operator refuse them before solving.
    assert!(matches!(SteadyFlow::new(cfg, std::slice::from_ref(&outside)), Err(FlowError::Shape(ShapeError::LeavesDomain { .. }))));
    let op = SteadyForce::new(cfg, vec![fourier()], cfg.rest(), [10, 30, 10, 30]).unwrap();
    let mut y = [0.0; 2];
    op.forward(&negative_params(), &[], &mut y);
    assert!(y.iter().all(|v| v.is_nan()), "{y:?}");
    assert!(matches!(op.take_error(), Some(OpError::Input(m)) if m.as_str().contains("the radius is") && m.as_str().contains("not positive")));
}

/// Parameters of [`fourier`]'s kind whose radius turns negative.
fn negative_params() -> Vec<f64> {
    let mut p = fourier().params();
    p[3] = 0.08;
    p
}
