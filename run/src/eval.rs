//! `saver eval`: runs a trained policy on fresh episodes and says how well it does:
//! success rate, episode lengths, returns and the final distance to the goal per
//! state-aligned coordinate; with `--trajectory`, a picture of what it does (2-D envs).

use crate::figures::register_font;
use anyhow::{bail, Context, Result};
use clap::Args;
use plotters::prelude::*;
use saver_core::config::RunConfig;
use saver_core::link::{ActorSettings, PolicyWeights};
use saver_core::rng::{rng_for, streams};
use saver_proto::NamedTensor;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// `saver eval` flags.
#[derive(Args, Clone, Debug)]
pub struct EvalArgs {
    /// A run folder (its config.toml and checkpoint) or a weights file (`saver weights
    /// --out`, or the learner's weights directory), which says what it is.
    #[arg(value_name = "RUN_DIR|WEIGHTS")]
    pub source: PathBuf,
    /// Episodes to run.
    #[arg(long, default_value_t = 100, value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
    pub episodes: u32,
    /// Act with the most likely action (μ; the largest logit) instead of sampling.
    #[arg(long)]
    pub deterministic: bool,
    /// Seed of the episodes' starts (and of the sampled actions).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
    /// Draw the first episodes' paths of the state-aligned position and the goal into
    /// this PNG (the arm's hand, angle d = 2; for d > 2 the first two coordinates).
    #[arg(long, value_name = "PNG")]
    pub trajectory: Option<PathBuf>,
}

/// How a policy did.
#[derive(Clone, Debug, PartialEq)]
pub struct EvalReport {
    /// The env.
    pub env: String,
    /// Episodes run.
    pub episodes: u32,
    /// Episodes that reached the goal.
    pub successes: u32,
    /// Each episode's length.
    pub lengths: Vec<u32>,
    /// Each episode's undiscounted scalar return.
    pub returns: Vec<f32>,
    /// Mean over episodes of |p − g| per state-aligned coordinate at the episode's end.
    pub final_distance: Vec<f32>,
}

/// The path of the state-aligned position in one episode, and its goal.
pub struct Path2 {
    /// Positions, the first one included.
    pub points: Vec<Vec<f32>>,
    /// The goal.
    pub goal: Vec<f32>,
}

/// Episodes the trajectory picture shows.
const PATHS: usize = 8;

/// Runs `settings.policy` with `weights` for `episodes` episodes of the preset env.
pub fn evaluate(
    settings: &ActorSettings,
    weights: Arc<PolicyWeights>,
    episodes: u32,
    deterministic: bool,
    seed: u64,
) -> Result<(EvalReport, Vec<Path2>)> {
    let mut env = settings.env.make(settings.max_episode_steps)?;
    let mut policy = settings.policy.acting(weights)?;
    let l = settings.env.layout();
    let aligned = l.aligned_start..l.aligned_start + l.aligned_dim;
    let mut rng = rng_for(seed, streams::EVAL);
    let (mut obs, mut action, mut payload) = (vec![0.0; l.obs_dim], Vec::new(), Vec::new());
    let mut report = EvalReport {
        env: settings.env.to_string(),
        episodes,
        successes: 0,
        lengths: Vec::new(),
        returns: Vec::new(),
        final_distance: vec![0.0; l.aligned_dim],
    };
    let mut paths = Vec::new();
    for e in 0..episodes {
        env.reset(&mut rng, &mut obs);
        let goal = env.goal();
        let mut path = vec![obs[aligned.clone()].to_vec()];
        let mut ret = 0.0f32;
        loop {
            if deterministic {
                policy.act_deterministic(&obs, &mut action);
            } else {
                policy.act(&obs, &mut rng, &mut action, &mut payload);
            }
            let step = env.step(&action, &mut obs);
            ret += step.vector_reward.iter().sum::<f32>();
            path.push(obs[aligned.clone()].to_vec());
            if step.done() {
                report.successes += u32::from(step.success);
                report.lengths.push(env.steps());
                break;
            }
        }
        report.returns.push(ret);
        for (d, (p, g)) in report
            .final_distance
            .iter_mut()
            .zip(obs[aligned.clone()].iter().zip(&goal))
        {
            *d += (p - g).abs() / episodes as f32;
        }
        if (e as usize) < PATHS {
            paths.push(Path2 { points: path, goal });
        }
    }
    Ok((report, paths))
}

/// Episodes of the learner's periodic evaluation (best.safetensors, eval.csv).
pub const LEARNER_EVAL_EPISODES: u32 = 10;
/// Updates between the learner's evaluations.
pub const LEARNER_EVAL_EVERY: u64 = 1000;

/// The learner's evaluator of `config`'s preset env: the mean return and success
/// rate of [`LEARNER_EVAL_EPISODES`] deterministic episodes from the same starts (seed
/// 0 of the evaluation stream) every time; `None` for a custom env, which only its
/// actors can step.
pub fn learner_evaluator(config: &RunConfig) -> Option<saver_learner::best::Evaluator> {
    config.env.kind()?;
    let settings = ActorSettings::of(config);
    Some(Box::new(move |w| {
        let n = LEARNER_EVAL_EPISODES;
        let (r, _) = evaluate(&settings, w, n, true, 0)
            .map_err(|e| saver_core::CoreError::Config(format!("evaluating: {e:#}")))?;
        Ok(saver_learner::best::Evaluation {
            mean_return: r.returns.iter().sum::<f32>() / n as f32,
            success_rate: r.successes as f32 / n as f32,
            episodes: n,
        })
    }))
}

/// The run settings and weights `source` names: a run folder or a weights file. A run
/// folder's weights are its policy.safetensors (the newest, written with every
/// checkpoint, with whatever observation normaliser the policy reads through); a folder
/// without one (written before it existed) gives its checkpoint's agent, unless that
/// agent read normalised observations, whose mean and scale only the weights carry.
pub fn load(source: &Path) -> Result<(ActorSettings, Arc<PolicyWeights>)> {
    if !source.is_dir() {
        return load_file(source);
    }
    let cfg = source.join("config.toml");
    let text = std::fs::read_to_string(&cfg).with_context(|| {
        format!(
            "reading {} (is {} a run folder?)",
            cfg.display(),
            source.display()
        )
    })?;
    let config =
        RunConfig::from_toml(&text).with_context(|| format!("reading {}", cfg.display()))?;
    let settings = ActorSettings::of(&config);
    let policy = source.join(saver_learner::best::POLICY_FILE);
    if policy.is_file() {
        let (tensors, meta) = read_safetensors(&policy, "")?;
        return Ok((settings, weights_of(tensors, &meta)));
    }
    let ckpt = source.join("checkpoint.safetensors");
    let (tensors, meta) = read_safetensors(&ckpt, " (has the run saved one yet?)")?;
    if let Some(t) = tensors.iter().find(|t| t.name.contains(".obs_norm.")) {
        bail!(
            "{}: the run's agent reads normalised observations ({}), whose mean and scale \
             only its weights carry, and the folder has no {}: evaluate a weights file of \
             the run instead",
            ckpt.display(),
            t.name,
            saver_learner::best::POLICY_FILE
        );
    }
    let agent = tensors
        .into_iter()
        .filter(|t| t.name.starts_with("agent."))
        .collect();
    Ok((settings, weights_of(agent, &meta)))
}

/// The settings (from its metadata) and weights of a self-describing weights file.
fn load_file(source: &Path) -> Result<(ActorSettings, Arc<PolicyWeights>)> {
    let (tensors, meta) = read_safetensors(source, "")?;
    let settings = saver_core::link::settings_from_metadata(&meta).with_context(|| {
        format!(
            "{}: not a self-describing SAVER weights file",
            source.display()
        )
    })?;
    Ok((settings, weights_of(tensors, &meta)))
}

/// The tensors and metadata of the safetensors file `path` (`hint` follows a read error).
fn read_safetensors(
    path: &Path,
    hint: &str,
) -> Result<(Vec<NamedTensor>, HashMap<String, String>)> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}{hint}", path.display()))?;
    saver_proto::decode(&bytes).with_context(|| path.display().to_string())
}

/// Weights of `tensors` at the version the metadata names (0 where it names none).
fn weights_of(tensors: Vec<NamedTensor>, meta: &HashMap<String, String>) -> Arc<PolicyWeights> {
    let version = meta
        .get("version")
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    Arc::new(PolicyWeights { version, tensors })
}

/// The command that plays a custom env's policy file (only the env's own Python code
/// steps it).
pub fn enjoy_command(policy: &Path) -> String {
    format!(
        "saver-actor enjoy --factory MODULE:FUNCTION --weights {}",
        policy.display()
    )
}

/// Runs `saver eval`.
pub fn run(args: EvalArgs) -> Result<()> {
    let (settings, weights) = load(&args.source)?;
    if settings.env.kind().is_none() {
        let file = if args.source.is_dir() {
            args.source.join(saver_learner::best::POLICY_FILE)
        } else {
            args.source.clone()
        };
        bail!(
            "{} is a custom env, which only its own Python code can step: play these weights \
             there with `{}` (each deterministic episode's return and success; --video to \
             record it), or evaluate a running learner's versions with `saver-actor \
             evaluate` (docs/GUIDE.md \"Bring your own environment\")",
            settings.env,
            enjoy_command(&file)
        );
    }
    let version = weights.version;
    let (r, paths) = evaluate(
        &settings,
        weights,
        args.episodes,
        args.deterministic,
        args.seed,
    )?;
    let mut lengths = r.lengths.clone();
    lengths.sort_unstable();
    let pct = |q: f64| lengths[((lengths.len() - 1) as f64 * q).round() as usize];
    let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
    let mean_len = lengths.iter().map(|&l| l as f64).sum::<f64>() / lengths.len() as f64;
    if args.json {
        let j = serde_json::json!({
            "env": r.env,
            "algo": settings.algo.name(),
            "version": version,
            "episodes": r.episodes,
            "deterministic": args.deterministic,
            "success_rate": r.successes as f64 / r.episodes as f64,
            "mean_length": mean_len,
            "length_percentiles": {"p10": pct(0.1), "p50": pct(0.5), "p90": pct(0.9), "max": pct(1.0)},
            "mean_return": mean(&r.returns),
            "final_distance": r.final_distance,
        });
        crate::out!("{j}");
    } else {
        crate::out!(
            "{} {} (weights v{version}), {} episodes{}:",
            settings.algo.name(),
            r.env,
            r.episodes,
            if args.deterministic {
                ", deterministic"
            } else {
                ""
            }
        );
        crate::out!(
            "  success rate    {:.3} ({} of {})",
            r.successes as f64 / r.episodes as f64,
            r.successes,
            r.episodes
        );
        crate::out!(
            "  episode length  mean {mean_len:.1}; p10 {} p50 {} p90 {} max {}",
            pct(0.1),
            pct(0.5),
            pct(0.9),
            pct(1.0)
        );
        crate::out!("  mean return     {:.4}", mean(&r.returns));
        crate::out!(
            "  final |p - g|   {:?} (mean per coordinate)",
            r.final_distance
                .iter()
                .map(|d| (d * 1e4).round() / 1e4)
                .collect::<Vec<_>>()
        );
    }
    if let Some(png) = &args.trajectory {
        draw(&paths, &r.env, png)?;
        eprintln!(
            "trajectories of the first {} episodes in {}",
            paths.len(),
            png.display()
        );
    }
    Ok(())
}

/// Draws 2-D paths with their goals.
fn draw(paths: &[Path2], env: &str, png: &Path) -> Result<()> {
    let d = paths.first().map_or(0, |p| p.goal.len());
    if d < 2 {
        bail!("--trajectory draws two state-aligned coordinates; {env} has {d}");
    }
    let shown = if d == 2 {
        "paths".to_string()
    } else {
        format!("coordinates 0 and 1 of {d}")
    };
    register_font();
    let all = paths
        .iter()
        .flat_map(|p| p.points.iter().chain(std::iter::once(&p.goal)));
    let lim = all
        .flat_map(|p| p[..2].iter().map(|v| v.abs()))
        .fold(1.0f32, f32::max)
        * 1.05;
    let root = BitMapBackend::new(png, (640, 640)).into_drawing_area();
    root.fill(&WHITE)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            format!("{env}: {shown} (circle: start, cross: goal)"),
            ("sans-serif", 20),
        )
        .margin(12)
        .x_label_area_size(35)
        .y_label_area_size(45)
        .build_cartesian_2d(-lim..lim, -lim..lim)?;
    chart
        .configure_mesh()
        .label_style(("sans-serif", 13))
        .draw()?;
    for (i, p) in paths.iter().enumerate() {
        let color = Palette99::pick(i).to_rgba();
        chart.draw_series(LineSeries::new(
            p.points.iter().map(|v| (v[0], v[1])),
            color.stroke_width(2),
        ))?;
        let start = &p.points[0];
        chart.draw_series(std::iter::once(Circle::new(
            (start[0], start[1]),
            5,
            color.filled(),
        )))?;
        chart.draw_series(std::iter::once(Cross::new(
            (p.goal[0], p.goal[1]),
            7,
            color.stroke_width(2),
        )))?;
    }
    root.present()
        .with_context(|| format!("writing {}", png.display()))?;
    Ok(())
}
