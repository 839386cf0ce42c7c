//! `diffsim sweep SCENE --set KEY=V1,V2 … --out DIR`: the solver as a data
//! generator. Every combination of the values runs as its own scene, the
//! runs spread over the ranks of an `mpirun` (round robin: run `i` on rank
//! `i mod K`); each run writes what `diffsim run` writes into
//! `DIR/run-NNNN/`, and rank 0 writes one table of the runs with their
//! values, figures and times (`runs.csv`, and `runs.json` with `--json`).
//! The files do not depend on the number of ranks (the times aside).

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::CliError;
use super::scene::{Views, write_images, write_state, write_steady};
use diffsim::distributed::World;
use diffsim::files::OutDir;
use diffsim::scene::AnyScene;

/// Arguments of `diffsim sweep`.
#[derive(Debug, clap::Args)]
pub struct SweepArgs {
    /// The scene file (TOML; keys in docs/scenes.md).
    scene: PathBuf,
    /// A key of the scene and the values it takes, `KEY=V1,V2,…`: the key
    /// dotted as in the file (`buoyancy.coefficient`,
    /// `obstacles[0].radius`), the values TOML (`0.5`, `true`, `"name"`,
    /// `[1, 2]`; a bare word is a string). Repeat for more keys: every
    /// combination runs, the last key varying fastest.
    #[arg(long = "set", value_name = "KEY=V1,V2,...", required = true)]
    set: Vec<String>,
    /// Output directory: run-NNNN/ per run, runs.csv (and runs.json).
    #[arg(long, default_value = "out/sweep")]
    out: PathBuf,
    #[command(flatten)]
    overwrite: super::Overwrite,
    /// Also write the table as runs.json and print it as one JSON line.
    #[arg(long)]
    json: bool,
    /// No line per finished run.
    #[arg(long)]
    quiet: bool,
}

/// The most runs one sweep may hold.
const MAX_RUNS: usize = 100_000;

/// One finished (or failed) run, as the table lists it.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct RunRow {
    /// Its number (the order of the combinations).
    run: usize,
    /// Wall seconds of the simulation.
    time_s: f64,
    /// `ok`, or the error that stopped it.
    status: String,
    /// Named results: the loss when the scene declares one, the mean and
    /// largest magnitude of each field (stepped scenes), the force
    /// coefficients on each body (steady scenes).
    figures: Vec<(String, f64)>,
}

/// `diffsim sweep`.
pub(super) fn sweep(a: SweepArgs, world: &World) -> Result<(), CliError> {
    let text = diffsim::files::read_text(&a.scene, diffsim::scene::MAX_SCENE_BYTES, "scene file")?;
    let table: toml::Table = toml::from_str(&text).map_err(|e| diffsim::scene::SceneError::Syntax(diffsim::words::toml_error(&e, &text)))?;
    let axes: Vec<(String, Vec<toml::Value>)> = a.set.iter().map(|s| parse_set(s)).collect::<Result<_, _>>()?;
    for (k, (key, _)) in axes.iter().enumerate() {
        if axes[..k].iter().any(|(earlier, _)| earlier == key) {
            return Err(CliError::Argument { arg: "--set", reason: format!("`{key}` is given twice; list all its values once: {key}=V1,V2,…") });
        }
    }
    let count = axes.iter().try_fold(1usize, |n, (_, v)| n.checked_mul(v.len())).filter(|&n| n <= MAX_RUNS);
    let Some(count) = count else {
        return Err(CliError::Argument { arg: "--set", reason: format!("more than {MAX_RUNS} combinations") });
    };
    let dir = a.scene.parent().unwrap_or(Path::new("."));
    // Every combination is built (and so checked) before any runs.
    let texts: Result<Vec<String>, CliError> = (0..count)
        .map(|i| {
            let values = combination(&axes, i);
            let mut t = table.clone();
            for ((key, _), v) in axes.iter().zip(&values) {
                set_key(&mut t, key, v.clone()).map_err(|reason| CliError::Argument { arg: "--set", reason: format!("`{key}`: {reason}") })?;
            }
            let text =
                toml::to_string(&t).map_err(|e| CliError::Argument { arg: "--set", reason: format!("run {i}: cannot write the scene back as TOML: {e}") })?;
            // The scene is checked as rewritten, whose lines are not the
            // user's: the error names the file and the values instead.
            AnyScene::parse_in(&text, dir).map_err(|e| CliError::Argument {
                arg: "--set",
                reason: format!("run {i}: {} with {}: {}", a.scene.display(), label(&axes, &values), without_lines(e)),
            })?;
            Ok(text)
        })
        .collect::<Result<_, CliError>>();
    // Every rank builds every combination: they agree whether any failed,
    // so that one error line says it (not one per rank, each aborting).
    let failed = world.all_gather(&[f64::from(u8::from(texts.is_err()))]);
    if failed.iter().any(|&f| f != 0.0) && world.size() > 1 {
        let why = texts.err().unwrap_or_else(|| CliError::Argument { arg: "--set", reason: "another rank could not build the sweep's scenes".into() });
        return Err(CliError::EveryRank(Box::new(why)));
    }
    let texts = texts?;
    // Rank 0 claims the folder (locked, refused when another run's) and
    // makes every run's folder before any rank writes into one.
    let claimed = if world.is_root() {
        let extra: String = a.set.iter().map(|s| format!(" --set {s}")).collect();
        let out = super::scene::claim(&a.out, &a.scene, &format!(" swept{extra}"), a.overwrite)?;
        out.folders((0..count).map(|i| format!("run-{i:04}")))?;
        Some(out)
    } else {
        None
    };
    world.barrier();
    let mut mine = Vec::new();
    for i in (world.rank()..count).step_by(world.size()) {
        let row = run_one(&texts[i], dir, &a.out.join(format!("run-{i:04}")), i)?;
        if !a.quiet {
            eprintln!("run {i} of {count} ({}): {} in {:.2} s", label(&axes, &combination(&axes, i)), row.status, row.time_s);
            // A long sweep says so after its first run.
            let total = row.time_s * count.div_ceil(world.size()) as f64;
            if mine.is_empty() && world.is_root() && count > 1 && total > 60.0 {
                eprintln!("{count} runs over {} rank(s): about {} in all at this run's pace", world.size(), super::scene::duration(total));
            }
        }
        mine.push(row);
    }
    let garbled = |e: serde_json::Error| CliError::Argument { arg: "sweep", reason: format!("the ranks' tables could not be gathered: {e}") };
    let bytes = serde_json::to_vec(&mine).map_err(garbled)?;
    let (Some(parts), Some(out)) = (world.gather_bytes(&bytes), claimed) else { return Ok(()) };
    let mut rows: Vec<RunRow> = Vec::with_capacity(count);
    for p in parts {
        rows.extend(serde_json::from_slice::<Vec<RunRow>>(&p).map_err(garbled)?);
    }
    rows.sort_by_key(|r| r.run);
    write_table(&a, &out, &axes, &rows)?;
    out.finish()?;
    let failed = rows.iter().filter(|r| r.status != "ok").count();
    println!(
        "{count} runs ({failed} failed) over {} rank(s); wrote run-0000 … run-{:04}, runs.csv{} to {}",
        world.size(),
        count - 1,
        if a.json { ", runs.json" } else { "" },
        a.out.display()
    );
    if failed > 0 {
        return Err(CliError::Argument { arg: "scene", reason: format!("{failed} of {count} runs failed (their errors are in runs.csv)") });
    }
    Ok(())
}

/// Runs the scene `text` into `out`; a failed simulation is a row with its
/// error, a failed write an error.
fn run_one(text: &str, dir: &Path, out: &Path, run: usize) -> Result<RunRow, CliError> {
    // (A folder another rank may have made: written through link-safe
    // paths, not claimed.)
    let out = &out.to_path_buf();
    let scene = AnyScene::parse_in(text, dir)?;
    let start = std::time::Instant::now();
    let mut figures = Vec::new();
    let status = match scene {
        AnyScene::Stepped(scene) => {
            // The scene's own loss terms, added up as the run passes them.
            use diffsim::rollout::Loss;
            let terms = scene.loss.as_ref().map(|l| scene.loss_terms(l));
            let mut scratch = vec![0.0; scene.x0.len()];
            let mut loss = 0.0;
            let result = scene.run(|k, x| {
                if let Some(t) = &terms
                    && t.has_term(k, scene.steps)
                {
                    loss += t.term(k, x, &mut scratch);
                }
            });
            match result {
                Ok(x) => {
                    let time = start.elapsed().as_secs_f64();
                    if scene.loss.is_some() {
                        figures.push(("loss".to_string(), loss));
                    }
                    for &field in &scene.fields {
                        let v = &x[scene.domain.range(field)];
                        figures.push((format!("{}_mean", field.name()), v.iter().sum::<f64>() / v.len().max(1) as f64));
                        figures.push((format!("{}_max_abs", field.name()), diffsim_solvers::cg::max_abs(v)));
                    }
                    if let Some(status) = non_finite_figure(&mut figures) {
                        return Ok(RunRow { run, time_s: time, status, figures });
                    }
                    write_state(&scene, out, &x)?;
                    write_images(&scene, out, "", &x, Views::default())?;
                    return Ok(RunRow { run, time_s: time, status: "ok".into(), figures });
                }
                Err(e) => e.to_string(),
            }
        }
        AnyScene::Steady(scene) => match scene.solve() {
            Ok(r) => {
                let time = start.elapsed().as_secs_f64();
                let scale = scene.loss.as_ref().map_or(1.0, |l| l.scale);
                for (k, f) in r.forces.iter().enumerate() {
                    figures.push((format!("obstacles{k}_fx"), f[0]));
                    figures.push((format!("obstacles{k}_fy"), f[1]));
                    if scale != 1.0 {
                        figures.push((format!("obstacles{k}_cd"), scale * f[0]));
                        figures.push((format!("obstacles{k}_cl"), scale * f[1]));
                    }
                }
                if let Some(status) = non_finite_figure(&mut figures) {
                    return Ok(RunRow { run, time_s: time, status, figures });
                }
                write_steady(&scene, &r, out)?;
                return Ok(RunRow { run, time_s: time, status: "ok".into(), figures });
            }
            Err(e) => e.to_string(),
        },
    };
    Ok(RunRow { run, time_s: start.elapsed().as_secs_f64(), status, figures })
}

/// A figure that overflowed (a loss past 1e308) is its run's error, not a
/// number of the table: the status saying which, with the non-finite
/// figures removed; `None` when every figure is finite.
fn non_finite_figure(figures: &mut Vec<(String, f64)>) -> Option<String> {
    let (name, v) = figures.iter().find(|(_, v)| !v.is_finite())?;
    let status = format!("the {name} came out {v}");
    figures.retain(|(_, v)| v.is_finite());
    Some(status)
}

/// Writes runs.csv (and runs.json): one row per run, the swept values, the
/// status, the time and every figure any run has.
fn write_table(a: &SweepArgs, out: &OutDir, axes: &[(String, Vec<toml::Value>)], rows: &[RunRow]) -> Result<(), CliError> {
    let mut names: Vec<&str> = Vec::new();
    for r in rows {
        for (n, _) in &r.figures {
            if !names.contains(&n.as_str()) {
                names.push(n);
            }
        }
    }
    let quote = |s: &str| if s.contains([',', '"', '\n']) { format!("\"{}\"", s.replace('"', "\"\"")) } else { s.to_string() };
    let mut csv = std::iter::once("run".to_string())
        .chain(axes.iter().map(|(k, _)| quote(k)))
        .chain(["status", "time_s"].map(String::from))
        .chain(names.iter().map(|n| n.to_string()))
        .collect::<Vec<_>>()
        .join(",");
    csv.push('\n');
    let mut json = Vec::new();
    for r in rows {
        let values = combination(axes, r.run);
        let figure = |n: &str| r.figures.iter().find(|(m, _)| m == n).map(|(_, v)| *v);
        let mut cells = vec![r.run.to_string()];
        cells.extend(values.iter().map(|v| quote(&v.to_string())));
        cells.push(quote(&r.status));
        cells.push(format!("{:.4}", r.time_s));
        cells.extend(names.iter().map(|n| figure(n).map_or(String::new(), |v| format!("{v:.10e}"))));
        csv.push_str(&cells.join(","));
        csv.push('\n');
        let mut obj = serde_json::Map::new();
        obj.insert("run".into(), r.run.into());
        for ((k, _), v) in axes.iter().zip(&values) {
            obj.insert(k.clone(), serde_json::to_value(v).unwrap_or(serde_json::Value::Null));
        }
        obj.insert("status".into(), r.status.clone().into());
        obj.insert("time_s".into(), r.time_s.into());
        for (n, v) in &r.figures {
            obj.insert(n.clone(), (*v).into());
        }
        json.push(serde_json::Value::Object(obj));
    }
    let path = out.file("runs.csv")?;
    diffsim::files::write_atomic(&path, csv.as_bytes()).map_err(|source| CliError::Io { path: path.clone(), source })?;
    if a.json {
        let path = out.file("runs.json")?;
        let text = serde_json::Value::Array(json);
        diffsim::files::write_atomic(&path, format!("{text:#}\n").as_bytes()).map_err(|source| CliError::Io { path: path.clone(), source })?;
        println!("{text}");
    }
    Ok(())
}

/// A scene error without the line numbers of the rewritten text (the
/// key it names is the user's).
fn without_lines(e: diffsim::scene::SceneError) -> String {
    use diffsim::scene::SceneError;
    match e {
        SceneError::Key { key, reason, .. } => SceneError::Key { key, reason, line: None }.to_string(),
        SceneError::Syntax(text) => {
            // `line N: …` and the quoted source line `\n  N | …`.
            let first = text.lines().next().unwrap_or("");
            let first = first.strip_prefix("line ").and_then(|r| r.split_once(": ")).map_or(first, |(_, rest)| rest);
            format!("scene: {first}")
        }
        e => e.to_string(),
    }
}

/// The values of combination `i` (the last key varying fastest).
fn combination(axes: &[(String, Vec<toml::Value>)], mut i: usize) -> Vec<toml::Value> {
    let mut out = vec![toml::Value::Boolean(false); axes.len()];
    for (k, (_, values)) in axes.iter().enumerate().rev() {
        out[k] = values[i % values.len()].clone();
        i /= values.len();
    }
    out
}

/// `key=value, …` of a combination.
fn label(axes: &[(String, Vec<toml::Value>)], values: &[toml::Value]) -> String {
    axes.iter().zip(values).map(|((k, _), v)| format!("{k}={v}")).collect::<Vec<_>>().join(", ")
}

/// `KEY=V1,V2,…` into the key and its values (commas inside brackets,
/// braces or quotes belong to a value).
fn parse_set(s: &str) -> Result<(String, Vec<toml::Value>), CliError> {
    let bad = |reason: String| CliError::Argument { arg: "--set", reason };
    let Some((key, list)) = s.split_once('=') else {
        return Err(bad(format!("expected KEY=V1,V2,…, got \"{s}\"")));
    };
    let key = key.trim();
    if key.is_empty() || path_of(key).is_err() {
        return Err(bad(format!("`{key}` is not a key (dotted names, with [i] for an entry of an array: obstacles[0].radius)")));
    }
    let (mut values, mut depth, mut quoted, mut start) = (Vec::new(), 0i32, false, 0);
    let list_bytes = list.as_bytes();
    for (i, &c) in list_bytes.iter().enumerate() {
        match c {
            b'"' => quoted = !quoted,
            b'[' | b'{' if !quoted => depth += 1,
            b']' | b'}' if !quoted => depth -= 1,
            b',' if !quoted && depth == 0 => {
                values.push(&list[start..i]);
                start = i + 1;
            }
            _ => {}
        }
    }
    values.push(&list[start..]);
    let parsed: Vec<toml::Value> = values
        .iter()
        .map(|v| {
            let v = v.trim();
            if v.is_empty() {
                return Err(bad(format!("`{key}`: an empty value in \"{list}\"")));
            }
            match toml::from_str::<toml::Table>(&format!("v = {v}")) {
                Ok(mut t) => Ok(t.remove("v").expect("the key just written")),
                Err(_) if v.chars().all(|c| c.is_alphanumeric() || c == '_' || c == '-') => Ok(toml::Value::String(v.to_string())),
                Err(e) => Err(bad(format!("`{key}`: \"{v}\" is not a TOML value ({})", e.message()))),
            }
        })
        .collect::<Result<_, _>>()?;
    Ok((key.to_string(), parsed))
}

/// One step of a key's path: a table key, or an entry of an array.
enum Step<'a> {
    Key(&'a str),
    Index(usize),
}

/// `obstacles[0].radius` → `obstacles`, `[0]`, `radius`.
fn path_of(key: &str) -> Result<Vec<Step<'_>>, ()> {
    let mut steps = Vec::new();
    for part in key.split('.') {
        let (name, mut rest) = part.split_once('[').map_or((part, ""), |(n, r)| (n, r));
        if name.is_empty() || !name.chars().all(|c| c.is_alphanumeric() || c == '_' || c == '-') {
            return Err(());
        }
        steps.push(Step::Key(name));
        while !rest.is_empty() {
            let (index, after) = rest.split_once(']').ok_or(())?;
            steps.push(Step::Index(index.parse().map_err(|_| ())?));
            rest = match after {
                "" => "",
                a => a.strip_prefix('[').ok_or(())?,
            };
        }
    }
    Ok(steps)
}

/// Sets `key` in `table` to `value`; tables on the way are made when
/// missing (the scene's own checks then name a key it does not know), an
/// array entry must exist.
fn set_key(table: &mut toml::Table, key: &str, value: toml::Value) -> Result<(), String> {
    let steps = path_of(key).map_err(|()| "not a key".to_string())?;
    let empty = || toml::Value::Table(toml::Table::new());
    let Some(Step::Key(first)) = steps.first() else { return Err("not a key".into()) };
    let mut current = table.entry(first.to_string()).or_insert_with(empty);
    for step in &steps[1..] {
        current = match (current, step) {
            (toml::Value::Table(t), Step::Key(k)) => t.entry(k.to_string()).or_insert_with(empty),
            (toml::Value::Array(a), Step::Index(i)) => {
                let len = a.len();
                a.get_mut(*i).ok_or_else(|| format!("entry [{i}] does not exist (the scene has {len})"))?
            }
            (_, Step::Key(k)) => return Err(format!("`{k}` is inside a value that is not a table")),
            (_, Step::Index(i)) => return Err(format!("[{i}] indexes a value that is not an array")),
        };
    }
    *current = value;
    Ok(())
}
