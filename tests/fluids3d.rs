//! 3D fluid operators beyond P4's closed box: obstacles (solid cells from
//! shapes), their boundary condition and the projection that couples fluid
//! cells only, under the three gradient checks and against the hand
//! adjoint through a whole rollout.

use diffsim::check::{CheckParams, check_all};
use diffsim::op::{Forward, OperatorExt};
use diffsim::problems::smoke3d::{P4, Project3, SmokeStep3};
use diffsim::rollout::{Checkpointing, Workspace};
use diffsim_solvers::smoke::MacGrid;
use diffsim_solvers::smoke::Preconditioner;
use diffsim_solvers::smoke::divergence;
use diffsim_solvers::smoke::{Solid, open_faces, solid_cells};

use crate::p4::{field, state};

/// `(f(h) − f(−h)) / 2h`.
fn central(f: impl Fn(f64) -> f64, h: f64) -> f64 {
    (f(h) - f(-h)) / (2.0 * h)
}

/// A sphere and a box, away from each other and from the walls.
fn shapes(n: usize) -> Vec<Solid<3>> {
    let h = n as f64;
    vec![
        Solid::Ball { center: [0.35 * h, 0.5 * h, 0.5 * h], radius: 0.2 * h },
        Solid::Box { lower: [0.65 * h, 0.25 * h, 0.3 * h], upper: [0.8 * h, 0.5 * h, 0.6 * h] },
    ]
}

#[test]
fn shapes_cover_the_cells_they_should() {
    let n = 24;
    let cfg = MacGrid::p4(n);
    let h = n as f64;
    // A sphere of radius 0.3·N: its volume in cells to a few percent.
    let r = 0.3 * h;
    let ball = solid_cells(&cfg, &[Solid::Ball { center: [h / 2.0; 3], radius: r }]);
    let count = ball.iter().filter(|&&s| s).count() as f64;
    let exact = 4.0 / 3.0 * std::f64::consts::PI * r.powi(3);
    assert!((count - exact).abs() < 0.05 * exact, "sphere: {count} cells, volume {exact}");
    // A cylinder along each axis is the same set of cells turned.
    let cyl = |axis: usize| solid_cells(&cfg, &[Solid::Cylinder { axis, center: [0.4 * h, 0.4 * h, 0.4 * h], radius: 0.25 * h, extent: [2.0, 20.0] }]);
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
    let b = solid_cells(&cfg, &[Solid::Box { lower: [-5.0, 3.0, 20.0], upper: [2.0, 5.0, 30.0] }]);
    assert_eq!(b.iter().filter(|&&s| s).count(), 2 * 2 * 4);
}

#[test]
fn projection_with_obstacles_leaves_no_divergence_and_no_flow_into_solids() {
    let n = 16;
    let cfg = MacGrid::p4(n);
    let solid = solid_cells(&cfg, &shapes(n));
    let fluid: Vec<f64> = solid.iter().map(|&s| if s { 0.0 } else { 1.0 }).collect();
    let op = Project3::with_obstacles(cfg, 1e-12, 1000, Preconditioner::Multigrid, &solid);
    // Closed walls (the projection changes interior faces only).
    let mut x = state(&cfg, 7);
    let ns = cfg.n_s();
    diffsim_solvers::smoke::enforce_boundary(&cfg, &mut x[ns..]);
    let y = op.eval(&x, &[]);
    assert!(op.take_error().is_none());
    let (s, [u, v, w]) = cfg.split(&y);
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
        let open = &open_faces(&cfg, &fluid)[cfg.face_range(axis)];
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
        let cfg = MacGrid::p4(n);
        let solid = solid_cells(&cfg, &shapes(n));
        assert!(solid.iter().any(|&s| s), "n = {n}: the shapes cover no cell");
        let x = state(&cfg, 20 + n as u64);
        for precond in [Preconditioner::Multigrid, Preconditioner::None] {
            let r = check_all(&Project3::with_obstacles(cfg, 1e-13, 500, precond, &solid), &x, &[], &CheckParams::default());
            assert!(r.passed(), "projection n = {n} {precond}:\n{r}");
        }
        let step = SmokeStep3::new(cfg, 1e-13, 500, Preconditioner::Multigrid).with_obstacles(&solid);
        let r = check_all(&step, &x, &[], &CheckParams::default());
        assert!(r.passed(), "step n = {n}:\n{r}");
    }
}

#[test]
fn rollout_with_obstacles_enzyme_matches_the_hand_adjoint() {
    // P4 at 16³ over 6 steps with a sphere above the smoke: Enzyme's
    // explicit adjoint and the hand-written one, chained with the masked
    // projection's implicit adjoint, give the same gradient.
    let n = 16;
    let cfg = MacGrid::p4(n);
    let h = n as f64;
    let solid = solid_cells(&cfg, &[Solid::Ball { center: [0.5 * h, 0.55 * h, 0.5 * h], radius: 0.15 * h }]);
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
    use diffsim_solvers::smoke::{P4_SIZES, probe};
    let scene = Scene::parse(P4_SCENE).unwrap();
    assert_eq!(scene.effects, ["advection", "buoyancy", "pressure"]);
    let r = &P4_SIZES[0];
    assert_eq!((r.n, r.steps), (32, 10));
    let g = scene.gradient(scene.loss.as_ref().unwrap(), Checkpointing::Store).unwrap();
    let gs = &g.inputs[0].arrays[0].2;
    let l2 = gs.iter().map(|v| v * v).sum::<f64>().sqrt();
    assert!((g.loss - r.loss).abs() <= 1e-6 * r.loss, "loss {} vs {}", g.loss, r.loss);
    assert!((l2 - r.grad_l2).abs() <= 1e-6 * r.grad_l2, "‖∇L‖ {l2} vs {}", r.grad_l2);
    assert!((gs[0] - r.grad_0).abs() <= 1e-6 * r.grad_l2 && (gs[probe::<3>(32)] - r.grad_probe).abs() <= 1e-6 * r.grad_l2);
    assert_eq!(g.inputs[0].arrays[0].1, vec![32, 32, 32]);
}

#[test]
fn a_3d_scene_with_obstacles_and_inflow_has_the_gradient_of_its_loss() {
    use diffsim::scene::Scene;
    let text = r#"
[domain]
size = [10, 12, 9]

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
kind = "diffusion"
fields = ["smoke", "velocity"]
viscosity = 0.05
scheme = "implicit"
tolerance = 1e-13

[[effects]]
kind = "force"
value = [0.0, 0.0, 0.05]

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
    let fd = central(
        |d| {
            let mut q = p.clone();
            q[index] += d;
            scene.loss_value(loss, &scene.x0, &q).unwrap()
        },
        h,
    );
    let db = g.inputs[1].arrays[0].2[0];
    assert!((fd - db).abs() <= 1e-6 * fd.abs().max(1e-8), "∂L/∂b {db} vs finite differences {fd}");
    // A directional derivative along a smooth change of the initial smoke.
    let gs = &g.inputs[0].arrays[0].2;
    let dir: Vec<f64> = field(gs.len(), 5);
    let fd = central(
        |d| {
            // The smoke moved along `dir`, the velocity as it was.
            let x: Vec<f64> = scene.x0.iter().zip(dir.iter().chain(std::iter::repeat(&0.0))).map(|(x, v)| x + d * v).collect();
            scene.loss_value(loss, &x, &p).unwrap()
        },
        h,
    );
    let dot: f64 = gs.iter().zip(&dir).map(|(a, b)| a * b).sum();
    assert!((fd - dot).abs() <= 1e-6 * fd.abs(), "∂L/∂s₀·d {dot} vs finite differences {fd}");
}

#[test]
fn diffusion_in_3d_passes_all_checks() {
    use diffsim::fluids::{Diffuse, DiffuseExplicit, DiffuseImplicit};
    let cfg = MacGrid::new([6, 5, 4]).with_dt(0.5);
    let x = state(&cfg, 41);
    let explicit = Diffuse::in_box(cfg, true, true, DiffuseExplicit::on);
    let r = check_all(&explicit, &x, &[0.1], &CheckParams::default());
    assert!(r.passed(), "explicit diffusion:\n{r}");
    let implicit = Diffuse::in_box(cfg, true, true, |g| DiffuseImplicit::on(g, 1e-13, 500));
    let r = check_all(&implicit, &x, &[0.7], &CheckParams::default());
    assert!(r.passed(), "implicit diffusion:\n{r}");
}

#[test]
fn diffusion_in_3d_decays_a_mode_at_the_exact_rate() {
    use diffsim_solvers::diffusion::{Grid, ImplicitSolver, explicit, laplacian};
    // The cell lattice's Laplacian is the closed box's pressure matrix,
    // written apart (the multigrid's slab-by-slab product).
    let n = 8;
    let g = Grid::of_state(&MacGrid::p4(n))[0];
    let s = field(n * n * n, 3);
    let (mut a, mut b) = (vec![0.0; s.len()], vec![0.0; s.len()]);
    laplacian(&g, &s, &mut a);
    diffsim_solvers::multigrid::apply_box_matrix(n, n, &s, &mut b);
    let diff = a.iter().zip(&b).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    assert!(diff < 1e-12, "3D Laplacian against the box matrix: {diff:e}");
    // cos(π(k+½)/n) along z (constant in x, y) is an eigenvector of the
    // closed lattice's matrix with eigenvalue λ = 2 − 2cos(π/n): explicit
    // diffusion scales it by 1 − κλ, implicit by 1/(1 + κλ).
    let mode: Vec<f64> = (0..n * n * n).map(|c| (std::f64::consts::PI * ((c / (n * n)) as f64 + 0.5) / n as f64).cos()).collect();
    let lambda = 2.0 - 2.0 * (std::f64::consts::PI / n as f64).cos();
    let kappa = 0.15;
    let mut y = vec![0.0; mode.len()];
    explicit(&g, kappa, &mode, &mut y);
    let worst = y.iter().zip(&mode).map(|(y, m)| (y - (1.0 - kappa * lambda) * m).abs()).fold(0.0, f64::max);
    assert!(worst < 1e-13, "explicit: {worst:e}");
    let mut solver = ImplicitSolver::new(g, 1e-13, 500);
    solver.solve(kappa, &mode, &mut y).unwrap();
    let worst = y.iter().zip(&mode).map(|(y, m)| (y - m / (1.0 + kappa * lambda)).abs()).fold(0.0, f64::max);
    assert!(worst < 1e-11, "implicit: {worst:e}");
}

#[test]
fn projection_of_any_box_with_mic0_passes_the_checks() {
    use diffsim_solvers::smoke3d::Mic3;
    // A box whose sides all differ, with a sphere: MIC(0) of its own
    // matrix, the aggregation V-cycle on the fluid cells, none.
    let cfg = MacGrid::new([7, 9, 5]).with_dt(1.0);
    let solid = solid_cells(&cfg, &[Solid::Ball { center: [3.5, 4.5, 2.5], radius: 1.6 }]);
    assert!(solid.iter().any(|&s| s));
    let x = state(&cfg, 61);
    // Multigrid in a box whose sides all differ is the aggregation V-cycle.
    for precond in [Preconditioner::Mic0, Preconditioner::Multigrid, Preconditioner::None] {
        let r = check_all(&Project3::with_obstacles(cfg, 1e-13, 500, precond, &solid), &x, &[], &CheckParams::default());
        assert!(r.passed(), "projection {precond}:\n{r}");
    }
    // Divergence-free after projection, walls closed first.
    let mut x = x;
    let ns = cfg.n_s();
    diffsim_solvers::smoke::enforce_boundary(&cfg, &mut x[ns..]);
    let op = Project3::with_obstacles(cfg, 1e-12, 500, Preconditioner::Mic0, &solid);
    let y = op.eval(&x, &[]);
    let (_, [u, v, w]) = cfg.split(&y);
    let mut d = vec![0.0; cfg.n_s()];
    divergence(&cfg, [u, v, w], &mut d);
    assert!(d.iter().all(|d| d.abs() < 1e-9), "divergence left: {:e}", d.iter().fold(0.0f64, |m, d| m.max(d.abs())));
    // The factor is symmetric and positive (the CG needs both).
    let fluid: Vec<f64> = solid.iter().map(|&s| if s { 0.0 } else { 1.0 }).collect();
    let mut mic = Mic3::new(&cfg, Some(&fluid));
    crate::checks::assert_symmetric_positive("MIC(0)", cfg.n_s(), false, |r, z| mic.apply(r, z));
}

#[test]
fn iterations_per_preconditioner_in_3d() {
    // What each preconditioner costs in iterations on a 24³ cube with a
    // sphere (printed; the solves must converge): multigrid of the box on
    // the fluid cells, MIC(0) of the matrix, none.
    let n = 24;
    let cfg = MacGrid::p4(n);
    let solid = solid_cells(&cfg, &[Solid::Ball { center: [12.0, 14.0, 12.0], radius: 5.0 }]);
    let mut x = state(&cfg, 71);
    let ns = cfg.n_s();
    diffsim_solvers::smoke::enforce_boundary(&cfg, &mut x[ns..]);
    let mut counts = Vec::new();
    for precond in [Preconditioner::Multigrid, Preconditioner::Mic0, Preconditioner::None] {
        for obstacles in [false, true] {
            let op = if obstacles { Project3::with_obstacles(cfg, 1e-8, 2000, precond, &solid) } else { Project3::new(cfg, 1e-8, 2000, precond) };
            op.eval(&x, &[]);
            assert!(op.take_error().is_none(), "{precond} obstacles {obstacles}");
            counts.push(format!("{precond}{}: {}", if obstacles { " + sphere" } else { "" }, op.log.cg_forward.get()));
        }
    }
    eprintln!("CG iterations at 24³, tolerance 1e-8: {}", counts.join(", "));
}

#[test]
fn multigrid_takes_any_box_with_two_equal_sides() {
    use diffsim_solvers::multigrid::Multigrid;
    // Square slabs stacked along z, y and x (the field reordered so the
    // slabs come last): the projection passes the checks with obstacles,
    // and the V-cycle of a stack of slabs is symmetric and positive.
    for dims in [[8, 8, 12], [6, 10, 6], [10, 6, 6]] {
        let cfg = MacGrid::new([dims[0], dims[1], dims[2]]).with_dt(1.0);
        let solid = solid_cells(&cfg, &[Solid::Ball { center: [dims[0] as f64 / 2.0, dims[1] as f64 / 2.0, dims[2] as f64 / 2.0], radius: 1.8 }]);
        let op = Project3::with_obstacles(cfg, 1e-13, 500, Preconditioner::Multigrid, &solid);
        assert_eq!(op.preconditioner(), Preconditioner::Multigrid);
        let x = state(&cfg, 81);
        let r = check_all(&op, &x, &[], &CheckParams::default());
        assert!(r.passed(), "{dims:?}:\n{r}");
    }
    let (n, nz) = (8, 24);
    let mut mg = Multigrid::slabs(n, nz);
    assert!(mg.depth() >= 2);
    crate::checks::assert_symmetric_positive("slabs 8² × 24", n * n * nz, true, |r, z| mg.apply(r, z));
}

#[test]
fn a_3d_obstacle_mask_comes_from_a_npy_file() {
    use diffsim::scene::Scene;
    use npyz::WriterBuilder;
    // A mask [nz, ny, nx] with a solid slab across the middle of y, except
    // a hole; written as float64 like `diffsim run` writes volumes.
    let (nx, ny, nz) = (6, 8, 5);
    let mut mask = vec![0.0; nx * ny * nz];
    for k in 0..nz {
        for i in 0..nx {
            if (i, k) != (2, 2) {
                mask[(k * ny + 4) * nx + i] = 1.0;
            }
        }
    }
    let dir = std::env::temp_dir().join(format!("diffsim-mask-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = std::io::BufWriter::new(std::fs::File::create(dir.join("mask.npy")).unwrap());
    let mut w = npyz::WriteOptions::new().default_dtype().shape(&[nz as u64, ny as u64, nx as u64]).writer(file).begin_nd().unwrap();
    w.extend(mask.iter().copied()).unwrap();
    w.finish().unwrap();
    let text = r#"
[domain]
size = [6, 8, 5]
[time]
dt = 1.0
steps = 2
[fields.velocity]
init = { sine = { amplitude = 0.5, wavenumber = [1.0, 1.0, 1.0] } }
[[obstacles]]
npy = "mask.npy"
[[effects]]
kind = "pressure"
"#;
    let scene = Scene::parse_in(text, &dir).unwrap();
    let solid = scene.solid.as_ref().unwrap();
    assert_eq!(solid.iter().filter(|&&s| s).count(), nx * nz - 1);
    assert!(solid[(4 * ny + 4) * nx + 3] && !solid[(2 * ny + 4) * nx + 2]);
    // No flow through the slab's faces; and since the box is closed, the net
    // flux through the plane of the slab is zero, so the hole, its only
    // opening, carries none either.
    let x = scene.run(|_, _| {}).unwrap();
    let v = &x[scene.domain.range(diffsim::scene::Field::Velocity)][(nx + 1) * ny * nz..][..nx * (ny + 1) * nz];
    for k in 0..nz {
        for i in 0..nx {
            let face = (k * (ny + 1) + 4) * nx + i;
            if (i, k) == (2, 2) {
                assert!(v[face].abs() < 1e-8, "net flux through the hole {}", v[face]);
            } else {
                assert_eq!(v[face], 0.0, "flow into the slab at ({i}, {k})");
            }
        }
    }
    assert!(v.iter().any(|v| v.abs() > 1e-3), "the flow vanished");
    // A mask of the wrong shape is refused with the file named.
    let bad = text.replace("size = [6, 8, 5]", "size = [6, 8, 6]");
    let err = Scene::parse_in(&bad, &dir).unwrap_err().to_string();
    assert!(err.contains("mask.npy") && err.contains("shape"), "{err}");
}
