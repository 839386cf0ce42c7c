//! `train::trainer`: the one loop, against a loop written out by hand
//! (schedule, clipping, rule), bit for bit; resuming in the middle equals
//! running through; an observer stops it; errors leave the last update;
//! checkpoints come by the policy, a stop flag and at the end; the CSV log
//! of a resumed run is the uninterrupted run's.

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
    TrainerParams {
        first,
        iterations,
        schedule: Schedule::Cosine { start: 0.1, end: 0.001, over: 40 },
        clip: 5.0,
        same_state_every: 20,
        ..TrainerParams::default()
    }
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

/// Records the iterations the trainer asked it to save.
#[derive(Default)]
struct Saves(Vec<usize>);

impl<R: ?Sized> diffsim::train::Observer<R> for Saves {
    fn row(&mut self, _: &Row, _: &[f64], _: &R) -> Result<ControlFlow<()>, TrainError> {
        Ok(ControlFlow::Continue(()))
    }
    fn checkpoint(&mut self, iteration: usize, _: &[f64], _: &R) -> Result<(), TrainError> {
        self.0.push(iteration);
        Ok(())
    }
}

#[test]
fn checkpoints_follow_the_policy_a_stop_flag_and_the_end() {
    use diffsim::train::CheckpointPolicy;
    use std::sync::atomic::{AtomicBool, Ordering};
    let world = World::single();
    let every = |n: usize| TrainerParams { checkpoint: CheckpointPolicy { every: n, seconds: f64::INFINITY }, ..params(1, 23) };
    // Every 5 iterations, and after the last.
    let mut saves = Saves::default();
    let (mut adam, mut theta) = (Adam::new(AdamParams::default()), vec![0.0; 3]);
    Trainer::new(every(5), &world).run_observed(&mut adam, &mut theta, |it| Ok(batch(it)), &mut saves).unwrap();
    assert_eq!(saves.0, [5, 10, 15, 20, 23]);
    // By time: a zero interval saves after every iteration.
    let mut saves = Saves::default();
    let timed = TrainerParams { checkpoint: CheckpointPolicy { every: usize::MAX, seconds: 0.0 }, ..params(1, 4) };
    Trainer::new(timed, &world).run_observed(&mut adam, &mut theta, |it| Ok(batch(it)), &mut saves).unwrap();
    assert_eq!(saves.0, [1, 2, 3, 4]);
    // The flag (Ctrl-C's): the run saves after the iteration in progress and stops there.
    let flag = AtomicBool::new(false);
    let mut saves = Saves::default();
    let (mut adam, mut theta) = (Adam::new(AdamParams::default()), vec![0.0; 3]);
    let set_at_7 = |it: usize| {
        if it == 7 {
            flag.store(true, Ordering::SeqCst);
        }
        Ok(batch(it))
    };
    let info = Trainer::new(every(5), &world).stop_on(&flag).run_observed(&mut adam, &mut theta, set_at_7, &mut saves).unwrap();
    assert_eq!((info.last, info.stopped, &saves.0[..]), (7, true, &[5, 7][..]));
    // An observer that cannot save stops the run with its error.
    let failing = diffsim::train::save_with(|it: usize, _: &[f64], _: &Adam| Err(TrainError::Observer(format!("cannot write at {it}"))));
    let e = Trainer::new(every(3), &world).run_observed(&mut adam, &mut theta, |it| Ok(batch(it)), failing).unwrap_err();
    assert_eq!(e.to_string(), "cannot write at 3");
}

#[test]
fn the_csv_log_of_a_resumed_run_is_the_uninterrupted_runs() {
    use diffsim::train::CsvLog;
    let dir = std::env::temp_dir().join(format!("diffsim-csvlog-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let world = World::single();
    let run = |path: &std::path::Path, first: usize, iterations: usize, done: usize, adam: &mut Adam, theta: &mut Vec<f64>| {
        let mut log = CsvLog::resume(path, done).unwrap();
        Trainer::new(params(first, iterations), &world).run_observed(adam, theta, |it| Ok(batch(it)), &mut log).unwrap();
        log.flush().unwrap();
    };
    let fields = |path: &std::path::Path| -> Vec<(String, String, String)> {
        let text = std::fs::read_to_string(path).unwrap();
        let mut lines = text.lines();
        assert_eq!(lines.next(), Some(CsvLog::HEADER));
        // The times differ from run to run; the rest must not.
        lines
            .map(|l| {
                let f: Vec<&str> = l.split(',').collect();
                assert_eq!(f.len(), 4, "{l}");
                (f[0].to_string(), f[1].to_string(), f[2].to_string())
            })
            .collect()
    };
    let whole = dir.join("whole.csv");
    let (mut a, mut ta) = (Adam::new(AdamParams::default()), vec![0.0; 3]);
    run(&whole, 1, 20, 0, &mut a, &mut ta);
    // A run killed after logging iteration 12 but checkpointed at 9:
    // resumed from 9, the rows past it are dropped and written again.
    let parts = dir.join("parts.csv");
    let (mut b, mut tb) = (Adam::new(AdamParams::default()), vec![0.0; 3]);
    run(&parts, 1, 9, 0, &mut b, &mut tb);
    let (mut lost, mut tlost) = (b.clone(), tb.clone());
    run(&parts, 10, 3, 9, &mut lost, &mut tlost);
    assert_eq!(fields(&parts).len(), 12);
    run(&parts, 10, 11, 9, &mut b, &mut tb);
    assert_eq!(fields(&parts), fields(&whole));
    assert_eq!(fields(&whole).len(), 20);
    assert_eq!(tb, ta);
    std::fs::remove_dir_all(&dir).unwrap();
}
