//! Bad inputs and memory budgets: every malformed training configuration
//! in `tests/configs_bad/` is refused with its expected message (the
//! scenes' corpus is `tests/scenes_bad/`, replayed in `scenes.rs`), the
//! parser's words are put plainly and never echo a huge value, sizes parse,
//! and the checkpointing cost model counts what the rollouts really do.

use std::path::Path;

use diffsim::memory::{MemoryError, human_up, parse_bytes};
use diffsim::problems::burgers::P1;
use diffsim::rollout::plan::{Job, choose, estimate};
use diffsim::rollout::{Checkpointing, Rollout};
use diffsim::scene::{AnyScene, SceneError};
use diffsim_studies::config::TrainConfig;

fn corpus(dir: &str) -> Vec<(std::path::PathBuf, String, String)> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join(dir);
    let mut files: Vec<_> = std::fs::read_dir(root).unwrap().map(|e| e.unwrap().path()).filter(|p| p.extension().is_some_and(|e| e == "toml")).collect();
    files.sort();
    files
        .into_iter()
        .map(|path| {
            let text = std::fs::read_to_string(&path).unwrap();
            let expect =
                text.lines().next().and_then(|l| l.strip_prefix("# expect: ")).unwrap_or_else(|| panic!("{}: no `# expect:` line", path.display())).to_string();
            (path, text, expect)
        })
        .collect()
}

#[test]
fn malformed_training_configs_are_refused_by_key() {
    let all = corpus("tests/configs_bad");
    assert!(all.len() >= 8);
    for (path, text, expect) in &all {
        let err = TrainConfig::parse(text).map(|_| ()).expect_err(&path.display().to_string()).to_string();
        assert!(err.contains(expect.as_str()), "{}: expected `{expect}` in\n{err}", path.display());
    }
    // The corpus's base configuration itself is accepted (each file differs from it in one key).
    let base = &all.iter().find(|(p, _, _)| p.ends_with("key_typo.toml")).unwrap().1.replace("iteratons", "iterations");
    TrainConfig::parse(base).unwrap();
}

#[test]
fn parser_words_are_plain_and_short() {
    use diffsim::words::plain;
    let (key, text) = plain("invalid type: floating point `0.5`, expected an array of length 2\nin `velocity`");
    assert_eq!(key.as_deref(), Some("velocity"));
    assert_eq!(text, "expected a list of 2 values, got the number 0.5");
    assert_eq!(plain("invalid value: integer `-3`, expected usize").1, "expected a whole number, got the number -3");
    assert!(plain("wanted exactly 1 element, more than 1 element").1.ends_with("got several"));
    assert_eq!(plain("unknown field `viscosty`, expected one of `fields`, `viscosity`").1, "unknown key `viscosty`; did you mean `viscosity`?");
    // A name holding backticks (found by fuzzing): the choices are still found, the name cut.
    assert_eq!(plain("unknown variant `a`b`, expected `relu` or `tanh`").1, "unknown kind `a`b`; expected one of relu, tanh");
    // A value of half a megabyte in a scene: the message stays short.
    let scene = format!(
        "[domain]\nsize = [16, 16]\n[time]\ndt = 1.0\nsteps = 2\n[[effects]]\nkind = \"diffusion\"\nfields = [\"smoke\"]\nviscosity = \"{}\"\n",
        "x".repeat(500_000)
    );
    let err = AnyScene::parse_in(&scene, Path::new(".")).unwrap_err().to_string();
    assert!(
        err.len() < 1000 && err.contains("`effects[0].viscosity`: expected a number, got the string"),
        "{} characters: {}",
        err.len(),
        &err[..err.len().min(300)]
    );
    // So does a syntax error on a line of a megabyte.
    let err = AnyScene::parse_in(&format!("[domain]\nsize = [16, 16] {}\n", "y".repeat(1_000_000)), Path::new(".")).unwrap_err().to_string();
    assert!(err.len() < 1000, "{} characters", err.len());
}

#[test]
fn scene_files_are_read_with_a_limit() {
    let dir = std::env::temp_dir().join(format!("diffsim-inputs-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let big = dir.join("big.toml");
    std::fs::write(&big, format!("# {}\n", "z".repeat(2 << 20))).unwrap();
    let err = AnyScene::load(&big).unwrap_err();
    assert!(matches!(err, SceneError::Read(_)) && err.to_string().contains("more than the 1048576 bytes a scene file may have"), "{err}");
    let err = AnyScene::load(&dir).unwrap_err().to_string();
    assert!(err.contains("not a regular file (a folder)"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn sizes_parse_and_suggestions_round_up() {
    assert_eq!(parse_bytes("50MB").unwrap(), 50_000_000);
    assert_eq!(parse_bytes("2GiB").unwrap(), 2 << 30);
    assert_eq!(parse_bytes("1.5k").unwrap(), 1500);
    assert_eq!(parse_bytes(" 123456 ").unwrap(), 123_456);
    for bad in ["", "MB", "-5MB", "5 parsecs", "1e30TB", "nan"] {
        assert!(matches!(parse_bytes(bad), Err(MemoryError::Parse(_))), "{bad:?} parsed");
    }
    assert_eq!(human_up(57_020_000), "58MB");
    assert_eq!(human_up(1_234_000_000), "1.3GB");
    // A suggested budget parses back to at least the need.
    for need in [999u64, 57_020_000, 1_234_000_000, 98_765_432_100] {
        assert!(parse_bytes(&human_up(need)).unwrap() >= need, "{need}");
    }
}

#[test]
fn cost_model_counts_what_the_rollout_does() {
    // The model's states and step evaluations against the rollout's own
    // counters (one thread: the periodic model allows for two segments).
    let p = P1::new(64, 300);
    let op = diffsim::problems::burgers::BurgersHand(p.cfg);
    let r = Rollout::new(&op, &[], p.steps).unwrap();
    let modes = [
        Checkpointing::Store,
        Checkpointing::Periodic { every: 17 },
        Checkpointing::Binomial { snapshots: 1 },
        Checkpointing::Binomial { snapshots: 3 },
        Checkpointing::Binomial { snapshots: 9 },
    ];
    for mode in modes {
        let g = r.value_and_grad(&p.u0, &p.loss(), mode).unwrap();
        let plan = estimate(mode, &Job { steps: p.steps, state_bytes: 8 * 64, copies: 1, forward_s: 1e-6 });
        let (states, evals) = (g.stats.peak_states as u64, g.stats.step_evaluations as u64);
        match mode {
            Checkpointing::Periodic { every } => {
                assert!(plan.states >= states && plan.states <= states + every as u64 + 2, "{mode}: model {} states, measured {states}", plan.states);
                assert!(plan.evaluations.abs_diff(evals) <= every as u64, "{mode}: model {} evaluations, measured {evals}", plan.evaluations);
            }
            _ => {
                assert!(plan.states >= states && plan.states <= states + 2, "{mode}: model {} states, measured {states}", plan.states);
                assert_eq!(plan.evaluations, evals, "{mode}: evaluations");
            }
        }
    }
}

#[test]
fn the_budget_picks_the_mode() {
    let (steps, state) = (100_000, 16_384u64);
    let job = Job { steps, state_bytes: state, copies: 1, forward_s: 4e-7 };
    let base = diffsim::memory::BASE;
    // Plenty: the fastest of all (storing every state is not: 1.6 GB of
    // traffic costs more than recomputing).
    let rich = choose(&job, 0, 1 << 40, "P1").unwrap();
    assert!(rich.seconds <= estimate(Checkpointing::Store, &job).seconds && matches!(rich.mode, Checkpointing::Periodic { .. }), "{rich}");
    // 50 MB: the states of the chosen mode fit.
    let tight = choose(&job, 0, 50_000_000, "P1").unwrap();
    assert!(tight.bytes + base <= 50_000_000, "{tight}");
    // Three copies in 30 MB: binomial with few snapshots, slower.
    let three = Job { copies: 3, ..job };
    let least = choose(&three, 0, 30_000_000, "P1").unwrap();
    assert!(matches!(least.mode, Checkpointing::Binomial { .. }) && least.seconds > tight.seconds && least.bytes + base <= 30_000_000, "{least}");
    // Too small: refused with the smallest budget that fits.
    let err = choose(&job, 0, base + state, "P1's gradient").unwrap_err().to_string();
    assert!(err.starts_with("P1's gradient needs about") && err.contains("it would fit in --memory-budget"), "{err}");
}
