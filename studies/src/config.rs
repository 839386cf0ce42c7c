//! `diffsim train CONFIG`: the TOML file of one training run of a
//! correction network through the coarse Burgers solver (keys in
//! `docs/train.md`). Every mistake is a [`ConfigError`] naming the key.

use serde::Deserialize;

use crate::burgers::{Method, Setup, TrainParams};
use diffsim::nn::{Activation, Net, Padding, presets};

/// A training configuration as written.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainFile {
    /// The problem.
    pub problem: ProblemSpec,
    /// The data sets.
    #[serde(default)]
    pub data: DataSpec,
    /// The network.
    #[serde(default)]
    pub network: NetworkSpec,
    /// The optimisation.
    pub training: TrainingSpec,
}

/// `[problem]`: solver-in-the-loop on Burgers.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProblemSpec {
    /// `"burgers"`.
    pub kind: String,
    /// Coarse cells (default 32).
    #[serde(default = "d32")]
    pub cells: usize,
    /// Fine cells per coarse cell (default 8).
    #[serde(default = "d8")]
    pub refinement: usize,
    /// Fine steps per coarse step (default 4).
    #[serde(default = "d4")]
    pub time_refinement: usize,
    /// Viscosity, or a range `[lo, hi]` sampled per batch (then the data
    /// is generated on the fly).
    #[serde(default = "nu")]
    pub viscosity: Viscosity,
    /// Sine modes of the initial states (default 3).
    #[serde(default = "d3")]
    pub modes: usize,
}

/// One viscosity or a range.
#[derive(Debug)]
pub enum Viscosity {
    /// Fixed.
    One(f64),
    /// Sampled per batch.
    Range([f64; 2]),
}

impl<'de> Deserialize<'de> for Viscosity {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        use serde::de::Error;
        let number = |v: &toml::Value| v.as_float().or_else(|| v.as_integer().map(|i| i as f64));
        let value = toml::Value::deserialize(d)?;
        match &value {
            toml::Value::Array(a) if a.len() == 2 => {
                if let (Some(lo), Some(hi)) = (number(&a[0]), number(&a[1])) {
                    return Ok(Viscosity::Range([lo, hi]));
                }
            }
            v => {
                if let Some(x) = number(v) {
                    return Ok(Viscosity::One(x));
                }
            }
        }
        Err(D::Error::custom(format!("expected a number or a range [lo, hi], got {}", diffsim::files::shorten(&value.to_string(), diffsim::words::ECHO))))
    }
}

/// `[data]`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DataSpec {
    /// Training trajectories (fixed data; default 32).
    #[serde(default = "d32")]
    pub train: usize,
    /// Coarse steps per training trajectory (default 144).
    #[serde(default = "d144")]
    pub steps: usize,
    /// Test trajectories (default 8).
    #[serde(default = "d8")]
    pub test: usize,
    /// Coarse steps of the test rollouts (default 128).
    #[serde(default = "d128")]
    pub test_steps: usize,
}

impl Default for DataSpec {
    fn default() -> Self {
        Self { train: 32, steps: 144, test: 8, test_steps: 128 }
    }
}

/// `[network]`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NetworkSpec {
    /// `"conv"` (default), `"resnet"` or `"unet"`.
    #[serde(default = "conv")]
    pub preset: String,
    /// Channels of the conv stack (default `[1, 32, 32, 1]`; conv only).
    pub channels: Option<Vec<usize>>,
    /// Width of the resnet / U-Net (default 16; not for conv).
    pub width: Option<usize>,
    /// Residual blocks (default 2; resnet only).
    pub blocks: Option<usize>,
    /// Kernel width (odd, default 5).
    #[serde(default = "d5")]
    pub kernel: usize,
    /// `"tanh"` (default), `"relu"`, `"gelu"`, …
    #[serde(default = "tanh")]
    pub activation: Activation,
}

impl Default for NetworkSpec {
    fn default() -> Self {
        Self { preset: conv(), channels: None, width: None, blocks: None, kernel: 5, activation: Activation::Tanh }
    }
}

/// `[training]`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainingSpec {
    /// `"pre"`, `"noise"` or `"sol"`.
    pub method: String,
    /// Unrolled steps for `sol` (default 16).
    #[serde(default = "d16")]
    pub unroll: usize,
    /// Input noise for `noise` (default 0.02).
    #[serde(default = "noise")]
    pub noise: f64,
    /// Batch size (default 16).
    #[serde(default = "d16")]
    pub batch: usize,
    /// Gradient updates.
    pub iterations: usize,
    /// `"adam"` (default) or `"sgd"`.
    #[serde(default = "adam")]
    pub optimizer: String,
    /// Learning rate (default 1e-3).
    #[serde(default = "lr")]
    pub lr: f64,
    /// Final learning rate of a cosine decay over `iterations` (default: `lr`, constant).
    pub lr_end: Option<f64>,
    /// Clip the gradient norm to this (default 10).
    #[serde(default = "clip")]
    pub clip: f64,
    /// Seed (default 1).
    #[serde(default = "one")]
    pub seed: u64,
}

macro_rules! defaults {
    ($($name:ident: $t:ty = $v:expr;)*) => { $(fn $name() -> $t { $v })* };
}
defaults! {
    d3: usize = 3; d4: usize = 4; d5: usize = 5; d8: usize = 8; d16: usize = 16; d32: usize = 32; d128: usize = 128; d144: usize = 144;
    nu: Viscosity = Viscosity::One(0.01); conv: String = "conv".into(); tanh: Activation = Activation::Tanh;
    noise: f64 = 0.02; adam: String = "adam".into(); lr: f64 = 1e-3; clip: f64 = 10.0; one: u64 = 1;
}

/// A configuration that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// Malformed TOML or a wrong type (the message names the line).
    #[error("training config: {0}")]
    Syntax(String),
    /// The run would not fit the memory budget.
    #[error("training config: {0}")]
    Memory(#[from] diffsim::memory::MemoryError),
    /// A value the run cannot use.
    #[error("training config: `{key}`: {reason}")]
    Key {
        /// The key.
        key: &'static str,
        /// What is wrong.
        reason: String,
    },
}

/// A checked configuration.
#[derive(Debug)]
pub struct TrainConfig {
    /// Grids (with the lower viscosity when it is a range).
    pub setup: Setup,
    /// The viscosity range when sampled per batch.
    pub nu_range: Option<(f64, f64)>,
    /// Data sizes.
    pub data: DataSpec,
    /// The network.
    pub net: Net,
    /// Optimisation settings.
    pub settings: TrainParams,
    /// `"adam"` or `"sgd"`.
    pub optimizer: String,
}

fn positive(key: &'static str, v: usize) -> Result<usize, ConfigError> {
    if v >= 1 { Ok(v) } else { Err(ConfigError::Key { key, reason: "must be at least 1".into() }) }
}

/// Widest layer (channels) a network may have.
const MAX_WIDTH: usize = 4096;
/// Most layers (conv) or blocks (resnet) a network may have.
const MAX_LAYERS: usize = 64;

fn at_most(key: &'static str, v: usize, max: usize) -> Result<usize, ConfigError> {
    if v <= max { Ok(v) } else { Err(ConfigError::Key { key, reason: format!("{v} is more than the {max} allowed") }) }
}

fn rate(key: &'static str, v: f64) -> Result<f64, ConfigError> {
    if v.is_finite() && v > 0.0 { Ok(v) } else { Err(ConfigError::Key { key, reason: format!("must be a positive finite number, got {v}") }) }
}

impl TrainConfig {
    /// Number of network parameters.
    pub fn net_params(&self) -> usize {
        diffsim::op::Operator::n_params(&self.net)
    }

    /// Parses and checks a configuration.
    pub fn parse(text: &str) -> Result<Self, ConfigError> {
        let f: TrainFile = toml::from_str(text).map_err(|e| ConfigError::Syntax(diffsim::words::toml_error(&e, text)))?;
        let p = &f.problem;
        if p.kind != "burgers" {
            return Err(ConfigError::Key { key: "problem.kind", reason: diffsim::words::unknown("problem", &p.kind, &["burgers"]) });
        }
        let cells = positive("problem.cells", p.cells)?;
        if cells < 3 {
            return Err(ConfigError::Key { key: "problem.cells", reason: "need at least 3".into() });
        }
        let (lo, range) = match p.viscosity {
            Viscosity::One(v) => (rate("problem.viscosity", v)?, None),
            Viscosity::Range([a, b]) => {
                let (a, b) = (rate("problem.viscosity", a)?, rate("problem.viscosity", b)?);
                if a > b {
                    return Err(ConfigError::Key { key: "problem.viscosity", reason: format!("the range [{a}, {b}] is empty") });
                }
                (a, Some((a, b)))
            }
        };
        // The data and the fine solver's arrays, checked before anything is allocated.
        let (d, fine) = (&f.data, p.refinement as u64);
        let trajectories =
            (d.train as u64).checked_mul(d.steps as u64 + 1).zip((d.test as u64).checked_mul(d.test_steps as u64 + 1)).and_then(|(a, b)| a.checked_add(b));
        let data = trajectories.and_then(|t| diffsim::memory::f64s(&[t, cells as u64]));
        let solver = diffsim::memory::f64s(&[cells as u64, fine, 16]);
        let detail = format!("{} training and {} test trajectories of {cells} cells, a fine grid of {cells}×{fine} cells", d.train, d.test);
        diffsim::memory::check("the training data", detail, data.zip(solver).and_then(|(a, b)| a.checked_add(b)), None)?;
        let setup = Setup::new(
            cells,
            positive("problem.refinement", p.refinement)?,
            positive("problem.time_refinement", p.time_refinement)?,
            lo,
            positive("problem.modes", p.modes)?,
        );
        let n = &f.network;
        let k = n.kernel;
        if k % 2 == 0 || k == 0 {
            return Err(ConfigError::Key { key: "network.kernel", reason: format!("must be odd, got {k}") });
        }
        if k > cells {
            return Err(ConfigError::Key { key: "network.kernel", reason: format!("a kernel of {k} cells is wider than the grid of {cells} cells") });
        }
        // A key the chosen preset does not read is an error, not ignored.
        let unused = |key: &'static str, given: bool, used_by: &str| -> Result<(), ConfigError> {
            if given { Err(ConfigError::Key { key, reason: format!("the {} preset does not use it (only {used_by})", n.preset) }) } else { Ok(()) }
        };
        let width = |n: &NetworkSpec| positive("network.width", n.width.unwrap_or(16)).and_then(|w| at_most("network.width", w, MAX_WIDTH));
        let net = match n.preset.as_str() {
            "conv" => {
                unused("network.width", n.width.is_some(), "resnet and unet")?;
                unused("network.blocks", n.blocks.is_some(), "resnet")?;
                let channels = n.channels.clone().unwrap_or_else(|| vec![1, 32, 32, 1]);
                if channels.len() < 2 || channels[0] != 1 || *channels.last().unwrap_or(&0) != 1 {
                    return Err(ConfigError::Key { key: "network.channels", reason: "must start and end with 1 (the state has one channel)".into() });
                }
                if channels.len() > MAX_LAYERS {
                    return Err(ConfigError::Key { key: "network.channels", reason: format!("{} layers; at most {MAX_LAYERS}", channels.len()) });
                }
                for &c in &channels {
                    positive("network.channels", c)?;
                    at_most("network.channels", c, MAX_WIDTH)?;
                }
                presets::conv_stack_1d(cells, &channels, k, Padding::Periodic, n.activation)
            }
            "resnet" => {
                unused("network.channels", n.channels.is_some(), "conv")?;
                let blocks = at_most("network.blocks", n.blocks.unwrap_or(2), MAX_LAYERS)?;
                presets::resnet_1d(cells, 1, 1, width(n)?, blocks, k, Padding::Periodic, n.activation)
            }
            "unet" => {
                unused("network.channels", n.channels.is_some(), "conv")?;
                unused("network.blocks", n.blocks.is_some(), "resnet")?;
                if cells % 2 != 0 {
                    return Err(ConfigError::Key { key: "network.preset", reason: format!("a U-Net needs an even number of cells, got {cells}") });
                }
                presets::unet_1d(cells, 1, 1, width(n)?, k, Padding::Periodic, n.activation)
            }
            other => return Err(ConfigError::Key { key: "network.preset", reason: diffsim::words::unknown("preset", other, &["conv", "resnet", "unet"]) }),
        }
        .map_err(|e| ConfigError::Key { key: "network", reason: e.to_string() })?;
        let t = &f.training;
        let method = match t.method.as_str() {
            "pre" => Method::Pre,
            "noise" => {
                if !(t.noise.is_finite() && t.noise >= 0.0) {
                    return Err(ConfigError::Key { key: "training.noise", reason: format!("must be finite and ≥ 0, got {}", t.noise) });
                }
                Method::Noise(t.noise)
            }
            "sol" => Method::Sol(positive("training.unroll", t.unroll)?),
            other => return Err(ConfigError::Key { key: "training.method", reason: diffsim::words::unknown("method", other, &["pre", "noise", "sol"]) }),
        };
        if f.data.steps <= method.unroll() && range.is_none() {
            return Err(ConfigError::Key {
                key: "data.steps",
                reason: format!("trajectories of {} steps are too short to unroll {}", f.data.steps, method.unroll()),
            });
        }
        if t.optimizer != "adam" && t.optimizer != "sgd" {
            return Err(ConfigError::Key { key: "training.optimizer", reason: diffsim::words::unknown("optimizer", &t.optimizer, &["adam", "sgd"]) });
        }
        let settings = TrainParams {
            method,
            batch: positive("training.batch", t.batch)?,
            iterations: positive("training.iterations", t.iterations)?,
            lr: rate("training.lr", t.lr)?,
            lr_end: match t.lr_end {
                Some(v) => rate("training.lr_end", v)?,
                None => t.lr,
            },
            decay_over: t.iterations,
            clip: rate("training.clip", t.clip)?,
            seed: t.seed,
            first: 1,
        };
        positive("data.train", f.data.train)?;
        positive("data.test", f.data.test)?;
        positive("data.test_steps", f.data.test_steps)?;
        Ok(Self { setup, nu_range: range, data: f.data, net, settings, optimizer: t.optimizer.clone() })
    }
}
