//! `train::trainer`: the one loop, against a loop written out by hand
//! (schedule, clipping, rule), bit for bit; resuming in the middle equals
//! running through; an observer stops it; errors leave the last update.

use std::ops::ControlFlow;

use diffsim::distributed::World;
use diffsim::train::trainer::Row;
use diffsim::train::{Adam, AdamParams, FnObjective, Objective, Schedule, TrainError, Trainer, TrainerParams, UpdateRule, clip_by_norm};

/// A quadratic bowl with a different target per iteration (a stand-in for
/// mini-batches drawn from the iteration's seed): `½‖θ − c_it‖²·w`.
fn batch(it: usize) -> impl Objective {
    FnObjective {
        n: 3,
        f: move |th: &[f64]| -> Result<(f64, Vec<f64>), TrainError> {
            let c = [(it as f64 * 0.7).sin(), 1.0 + (it as f64 * 0.3).cos(), -0.5];
            let w = [30.0, 1.0, 0.1];
            let g: Vec<f64> = (0..3).map(|i| w[i] * (th[i] - c[i])).collect();
            Ok(((0..3).map(|i| 0.5 * w[i] * (th[i] - c[i]).powi(2)).sum(), g))
        },
    }
}

fn params(first: usize, iterations: usize) -> TrainerParams {
    TrainerParams { first, iterations, schedule: Schedule::Cosine { start: 0.1, end: 0.001, over: 40 }, clip: 5.0, same_state_every: 20 }
}

#[test]
fn the_trainer_takes_the_steps_of_a_loop_written_out() {
    let world = World::single();
    let mut adam = Adam::new(AdamParams::default());
    let mut theta = vec![0.0; 3];
    let mut rows: Vec<Row> = Vec::new();
    let info = Trainer::new(params(1, 50), &world)
        .run(
            &mut adam,
            &mut theta,
            |it| Ok(batch(it)),
            |row, _, _| {
                rows.push(*row);
                ControlFlow::Continue(())
            },
        )
        .unwrap();
    assert_eq!((info.last, info.stopped, rows.len()), (50, false, 50));
    // The same by hand.
    let mut by_hand = Adam::new(AdamParams::default());
    let mut reference = vec![0.0; 3];
    for it in 1..=50 {
        let f = (it - 1) as f64 / 40.0;
        let lr = 0.001 + 0.5 * (0.1 - 0.001) * (1.0 + (std::f64::consts::PI * f.min(1.0)).cos());
        by_hand.params.lr = lr;
        let (loss, mut g) = batch(it).loss_and_gradient(&reference).unwrap();
        let norm = clip_by_norm(&mut g, 5.0);
        by_hand.update(&mut reference, &g);
        let row = rows[it - 1];
        assert_eq!((row.iteration, row.loss, row.grad_norm, row.lr), (it, loss, Some(norm), Some(lr)));
    }
    assert_eq!(theta, reference);
    // Clipping happened (the first gradients exceed 5) and the schedule ran.
    assert!(rows[0].grad_norm.unwrap() > 5.0 && rows[49].lr == Some(0.001));
}

#[test]
fn a_resumed_run_equals_one_run_through_and_an_observer_stops_it() {
    let world = World::single();
    let run = |first: usize, iterations: usize, adam: &mut Adam, theta: &mut Vec<f64>| {
        Trainer::new(params(first, iterations), &world).run(adam, theta, |it| Ok(batch(it)), |_, _, _| ControlFlow::Continue(())).unwrap()
    };
    let (mut a, mut whole) = (Adam::new(AdamParams::default()), vec![0.0; 3]);
    run(1, 30, &mut a, &mut whole);
    // Stopped by the observer after iteration 12 (a checkpoint, Ctrl-C) …
    let (mut b, mut parts) = (Adam::new(AdamParams::default()), vec![0.0; 3]);
    let info = Trainer::new(params(1, 30), &world)
        .run(&mut b, &mut parts, |it| Ok(batch(it)), |row, _, _| if row.iteration == 12 { ControlFlow::Break(()) } else { ControlFlow::Continue(()) })
        .unwrap();
    assert_eq!((info.last, info.stopped), (12, true));
    // … and continued from there (the rule's state kept, as a checkpoint keeps it).
    let info = run(13, 18, &mut b, &mut parts);
    assert_eq!((info.last, info.stopped), (30, false));
    assert_eq!(parts, whole);
    assert_eq!(b.state_values(), a.state_values());
}

#[test]
fn an_error_stops_the_run_with_the_last_update_kept() {
    let world = World::single();
    let mut adam = Adam::new(AdamParams::default());
    let mut theta = vec![0.0; 3];
    let mut kept = Vec::new();
    let e = Trainer::new(params(1, 10), &world)
        .run(
            &mut adam,
            &mut theta,
            |it| if it < 4 { Ok(batch(it)) } else { Err(TrainError::Objective(format!("batch {it} cannot be drawn"))) },
            |_, th, _| {
                kept = th.to_vec();
                ControlFlow::Continue(())
            },
        )
        .unwrap_err();
    assert_eq!(e, TrainError::Objective("batch 4 cannot be drawn".into()));
    assert_eq!(theta, kept);
}
