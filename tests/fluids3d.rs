//! 3D fluid operators beyond P4's closed box: obstacles (solid cells from
//! shapes), their boundary condition and the projection that couples fluid
//! cells only, under the three gradient checks and against the hand
//! adjoint through a whole rollout.

use diffsim::check::{CheckOptions, check_all};
use diffsim::op::{Forward, OperatorExt};
use diffsim::problems::smoke3d::{P4, Project3, SmokeStep3};
use diffsim::rollout::{Checkpointing, Workspace};
use diffsim_solvers::smoke::Preconditioner;
use diffsim_solvers::smoke3d::{Smoke3d, Solid3, divergence, open_faces, solid_cells};

fn field(n: usize, seed: u64) -> Vec<f64> {
    (0..n).map(|k| (((k as f64 + 1.0) * 0.6180339887 * (seed as f64 + 0.7)).fract() - 0.5) * 2.0).collect()
}

/// Smoke in [0, 2], velocities of one sign per component with speeds in
/// [0.15, 0.45] (traces stay off sampling kinks, as in tests/p4.rs).
fn state(cfg: &Smoke3d, seed: u64) -> Vec<f64> {
    let (ns, nu, nv) = (cfg.n_s(), cfg.n_face(0), cfg.n_face(1));
    field(cfg.n_state(), seed)
        .iter()
        .enumerate()
        .map(|(k, v)| {
            let speed = 0.3 + 0.15 * v;
            if k < ns {
                1.0 + v
            } else if k < ns + nu || k >= ns + nu + nv {
                speed
            } else {
                -speed
            }
        })
        .collect()
}

/// A sphere and a box, away from each other and from the walls.
fn shapes(n: usize) -> Vec<Solid3> {
    let h = n as f64;
    vec![
        Solid3::Sphere { center: [0.35 * h, 0.5 * h, 0.5 * h], radius: 0.2 * h },
        Solid3::Box { lower: [0.65 * h, 0.25 * h, 0.3 * h], upper: [0.8 * h, 0.5 * h, 0.6 * h] },
    ]
}

#[test]
fn shapes_cover_the_cells_they_should() {
    let n = 24;
    let cfg = Smoke3d::p4(n);
    let h = n as f64;
    // A sphere of radius 0.3·N: its volume in cells to a few percent.
    let r = 0.3 * h;
    let ball = solid_cells(&cfg, &[Solid3::Sphere { center: [h / 2.0; 3], radius: r }]);
    let count = ball.iter().filter(|&&s| s).count() as f64;
    let exact = 4.0 / 3.0 * std::f64::consts::PI * r.powi(3);
    assert!((count - exact).abs() < 0.05 * exact, "sphere: {count} cells, volume {exact}");
    // A cylinder along each axis is the same set of cells turned.
    let cyl = |axis: usize| solid_cells(&cfg, &[Solid3::Cylinder { axis, center: [0.4 * h, 0.4 * h, 0.4 * h], radius: 0.25 * h, extent: [2.0, 20.0] }]);
    let (cx, cz) = (cyl(0), cyl(2));
    let at = |i: usize, j: usize, k: usize| (k * n + j) * n + i;
    let mut cells = 0;
    for k in 0..n {
        for j in 0..n {
            for i in 0..n {
                // Along z at (i, j, k) is along x at (k, j, i) with x and z swapped.
                assert_eq!(cz[at(i, j, k)], cx[at(k, j, i)], "cylinder cell ({i}, {j}, {k})");
                cells += cz[at(i, j, k)] as usize;
            }
        }
    }
    // 18 slabs (centres 2.5..=19.5) of the disc's cells.
    let disc = (0..n * n).filter(|c| ((c % n) as f64 + 0.5 - 0.4 * h).powi(2) + ((c / n) as f64 + 0.5 - 0.4 * h).powi(2) <= (0.25 * h).powi(2)).count();
    assert!(disc > 100);
    assert_eq!(cells, 18 * disc, "cylinder cells");
    // A box is the cells whose centres lie inside, clipped to the domain.
    let b = solid_cells(&cfg, &[Solid3::Box { lower: [-5.0, 3.0, 20.0], upper: [2.0, 5.0, 30.0] }]);
    assert_eq!(b.iter().filter(|&&s| s).count(), 2 * 2 * 4);
}

#[test]
fn projection_with_obstacles_leaves_no_divergence_and_no_flow_into_solids() {
    let n = 16;
    let cfg = Smoke3d::p4(n);
    let solid = solid_cells(&cfg, &shapes(n));
    let fluid: Vec<f64> = solid.iter().map(|&s| if s { 0.0 } else { 1.0 }).collect();
    let op = Project3::with_obstacles(cfg, 1e-12, 1000, Preconditioner::Multigrid, &solid);
    // Closed walls (the projection changes interior faces only).
    let mut x = state(&cfg, 7);
    let [_, u, v, w] = cfg.split_mut(&mut x);
    diffsim_solvers::smoke3d::close_walls(&cfg, [u, v, w]);
    let y = op.eval(&x, &[]);
    assert!(op.take_error().is_none());
    let [s, u, v, w] = cfg.split(&y);
    let mut d = vec![0.0; cfg.n_s()];
    divergence(&cfg, [u, v, w], &mut d);
    let speed = u.iter().chain(v).chain(w).map(|v| v * v).sum::<f64>().sqrt();
    let worst = d.iter().fold(0.0f64, |m, d| m.max(d.abs()));
    assert!(worst <= 1e-9 * speed, "divergence {worst:e} (speed {speed:e})");
    // Solid cells hold no smoke and no face of theirs carries flow; the
    // fluid keeps its smoke.
    for (c, &sv) in s.iter().enumerate() {
        assert_eq!(sv == 0.0, solid[c] || x[c] == 0.0, "smoke at cell {c}");
    }
    for (axis, vel) in [u, v, w].into_iter().enumerate() {
        let open = &open_faces(&cfg, &fluid)[axis];
        for (f, (&vv, &o)) in vel.iter().zip(open).enumerate() {
            if o == 0.0 {
                assert_eq!(vv, 0.0, "axis {axis} face {f} touches a solid and carries {vv}");
            }
        }
    }
    // The obstacles change the flow: the masked projection is not the
    // closed box's.
    let plain = Project3::new(cfg, 1e-12, 1000, Preconditioner::Multigrid).eval(&x, &[]);
    assert!(plain.iter().zip(&y).any(|(a, b)| (a - b).abs() > 1e-3));
    eprintln!("3D projection with obstacles at {n}³: {} CG iterations (multigrid of the box on the fluid cells)", op.log.cg_forward.get());
}

#[test]
fn projection_and_step_with_obstacles_pass_all_checks() {
    for n in [6, 8] {
        let cfg = Smoke3d::p4(n);
        let solid = solid_cells(&cfg, &shapes(n));
        assert!(solid.iter().any(|&s| s), "n = {n}: the shapes cover no cell");
        let x = state(&cfg, 20 + n as u64);
        for precond in [Preconditioner::Multigrid, Preconditioner::None] {
            let r = check_all(&Project3::with_obstacles(cfg, 1e-13, 500, precond, &solid), &x, &[], &CheckOptions::default());
            assert!(r.passed(), "projection n = {n} {precond}:\n{r}");
        }
        let step = SmokeStep3::new(cfg, 1e-13, 500, Preconditioner::Multigrid).with_obstacles(&solid);
        let r = check_all(&step, &x, &[], &CheckOptions::default());
        assert!(r.passed(), "step n = {n}:\n{r}");
    }
}

#[test]
fn rollout_with_obstacles_enzyme_matches_the_hand_adjoint() {
    // P4 at 16³ over 6 steps with a sphere above the smoke: Enzyme's
    // explicit adjoint and the hand-written one, chained with the masked
    // projection's implicit adjoint, give the same gradient.
    let n = 16;
    let cfg = Smoke3d::p4(n);
    let h = n as f64;
    let solid = solid_cells(&cfg, &[Solid3::Sphere { center: [0.5 * h, 0.55 * h, 0.5 * h], radius: 0.15 * h }]);
    let run = |hand: bool| {
        let mut p = P4::new(n, 6, Preconditioner::Multigrid);
        p.step = p.step.with_obstacles(&solid);
        if hand {
            p = p.with_hand_adjoint();
        }
        let g = p.grad_in(&mut Workspace::new(), Checkpointing::Store).unwrap();
        (g.loss, p.smoke_gradient(&g).to_vec())
    };
    let (la, ga) = run(false);
    let (lb, gb) = run(true);
    let plain = P4::new(n, 6, Preconditioner::Multigrid).grad_in(&mut Workspace::new(), Checkpointing::Store).unwrap();
    assert!((la - plain.loss).abs() > 1e-6 * plain.loss, "the sphere does not change the loss ({la} vs {})", plain.loss);
    assert!((la - lb).abs() <= 1e-13 * la.abs(), "loss {la} vs {lb}");
    let scale = ga.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let diff = ga.iter().zip(&gb).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    assert!(diff <= 1e-10 * scale, "Enzyme and hand gradients differ by {diff:e} (scale {scale:e})");
    // No gradient reaches the initial smoke inside the solid (masked away).
    for (c, &s) in solid.iter().enumerate() {
        if s {
            assert_eq!(ga[c], 0.0, "gradient in solid cell {c}");
        }
    }
}

#[test]
fn buoyancy_and_inflow_pass_all_checks() {
    use diffsim::fluids3d::{Buoyancy3, Inflow3};
    let cfg = Smoke3d::new(6, 7, 5, 0.5);
    let x = state(&cfg, 31);
    for axis in 0..3 {
        let r = check_all(&Buoyancy3 { cfg, dt: 0.5, axis }, &x, &[0.3], &CheckOptions::default());
        assert!(r.passed(), "buoyancy along axis {axis}:\n{r}");
    }
    let inflow = Inflow3 { cfg, region: [0, 2, 1, 3, 2, 5] };
    let r = check_all(&inflow, &x, &[0.8, 0.1, 0.4, -0.2], &CheckOptions::default());
    assert!(r.passed(), "inflow:\n{r}");
    // The region's cells and faces are set, the rest passes through.
    let y = inflow.eval(&x, &[0.8, 0.1, 0.4, -0.2]);
    let cell = |i: usize, j: usize, k: usize| (k * 7 + j) * 6 + i;
    assert_eq!(y[cell(1, 2, 4)], 0.8);
    assert_eq!(y[cell(2, 2, 4)], x[cell(2, 2, 4)]);
    // The x-face between cells (1, 2, 4) and (2, 2, 4) (inside the region's
    // upper side) and the box's own left side (not set).
    let u = |i: usize, j: usize, k: usize| cfg.n_s() + (k * 7 + j) * 7 + i;
    assert_eq!(y[u(2, 2, 4)], 0.1);
    assert_eq!(y[u(0, 2, 4)], x[u(0, 2, 4)]);
}

/// P4 written as a scene file: the advection, buoyancy and projection as
/// three declared effects.
const P4_SCENE: &str = r#"
[domain]
size = [32, 32, 32]

[time]
dt = 1.0
steps = 10

[fields.smoke]
init = { sphere = { center = [16.0, 8.0, 16.0], radius = 4.0 } }
[fields.velocity]
init = "zero"

[[effects]]
kind = "advection"

[[effects]]
kind = "buoyancy"
coefficient = 0.1

[[effects]]
kind = "pressure"

[loss]
field = "smoke"
target = { sphere = { center = [16.0, 24.0, 16.0], radius = 4.0 } }
with_respect_to = ["smoke.init"]
"#;

#[test]
fn a_3d_scene_reproduces_the_p4_reference_table() {
    use diffsim::scene::Scene;
    use diffsim_solvers::smoke3d::{P4_SIZES, p4_mid};
    let scene = Scene::parse(P4_SCENE).unwrap();
    assert_eq!(scene.effects, ["advection", "buoyancy", "pressure"]);
    let r = &P4_SIZES[0];
    assert_eq!((r.n, r.steps), (32, 10));
    let g = scene.gradient(scene.loss.as_ref().unwrap(), Checkpointing::Store).unwrap();
    let gs = &g.inputs[0].arrays[0].2;
    let l2 = gs.iter().map(|v| v * v).sum::<f64>().sqrt();
    assert!((g.loss - r.loss).abs() <= 1e-6 * r.loss, "loss {} vs {}", g.loss, r.loss);
    assert!((l2 - r.grad_l2).abs() <= 1e-6 * r.grad_l2, "‖∇L‖ {l2} vs {}", r.grad_l2);
    assert!((gs[0] - r.grad_0).abs() <= 1e-6 * r.grad_l2 && (gs[p4_mid(32)] - r.grad_mid).abs() <= 1e-6 * r.grad_l2);
    assert_eq!(g.inputs[0].arrays[0].1, vec![32, 32, 32]);
}

#[test]
fn a_3d_scene_with_obstacles_and_inflow_has_the_gradient_of_its_loss() {
    use diffsim::scene::Scene;
    let text = r#"
[domain]
size = [10, 10, 10]

[time]
dt = 0.8
steps = 4

[fields.smoke]
init = { sphere = { center = [5.0, 3.0, 5.0], radius = 2.5 } }
[fields.velocity]
init = { uniform = [0.2, 0.3, -0.1] }

[[obstacles]]
cylinder = { center = [5.0, 7.0, 0.0], radius = 1.6, axis = "z", extent = [2.0, 8.0] }

[[effects]]
kind = "inflow"
region = { box = { lower = [4.0, 0.0, 4.0], upper = [6.0, 1.0, 6.0] } }
smoke = 1.0
velocity = [0.0, 0.5, 0.0]

[[effects]]
kind = "advection"

[[effects]]
kind = "buoyancy"
coefficient = 0.2
axis = "y"

[[effects]]
kind = "pressure"
tolerance = 1e-13

[loss]
field = "smoke"
target = { box = { lower = [3.0, 6.0, 3.0], upper = [7.0, 9.0, 7.0] } }
with_respect_to = ["smoke.init", "buoyancy.coefficient"]
"#;
    let scene = Scene::parse(text).unwrap();
    let loss = scene.loss.as_ref().unwrap();
    let g = scene.gradient(loss, Checkpointing::Store).unwrap();
    let p = scene.rollout_params();
    // ∂L/∂b against central differences of whole runs.
    let (_, index, _) = scene.named.iter().find(|(n, _, _)| n == "buoyancy.coefficient").unwrap().clone();
    let h = 1e-5;
    let at_b = |d: f64| {
        let mut q = p.clone();
        q[index] += d;
        scene.loss_value(loss, &scene.x0, &q).unwrap()
    };
    let fd = (at_b(h) - at_b(-h)) / (2.0 * h);
    let db = g.inputs[1].arrays[0].2[0];
    assert!((fd - db).abs() <= 1e-6 * fd.abs().max(1e-8), "∂L/∂b {db} vs finite differences {fd}");
    // A directional derivative along a smooth change of the initial smoke.
    let gs = &g.inputs[0].arrays[0].2;
    let dir: Vec<f64> = field(gs.len(), 5);
    let at_s = |d: f64| {
        let mut x = scene.x0.clone();
        for (x, v) in x.iter_mut().zip(&dir) {
            *x += d * v;
        }
        scene.loss_value(loss, &x, &p).unwrap()
    };
    let fd = (at_s(h) - at_s(-h)) / (2.0 * h);
    let dot: f64 = gs.iter().zip(&dir).map(|(a, b)| a * b).sum();
    assert!((fd - dot).abs() <= 1e-6 * fd.abs(), "∂L/∂s₀·d {dot} vs finite differences {fd}");
}
