//! `saver repro fig3|fig4|fig5`: one of the paper's experiments as a grid of `saver
//! train` processes (env, dimensions, SAVER with our defaults and with `--faithful`,
//! A2C, seeds), `--jobs` at a time, resumable (finished runs are skipped; a killed run
//! resumes from its checkpoint, as `saver train` does), then the figure and its table
//! (docs/ALGORITHM.md §12 for the settings; each run's config.toml names its PCPN).

use crate::figures;
use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

/// The paper's experiments.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Figure {
    /// Angle, d = 2, 4, 8, 16, 2.56 M steps, 3 seeds (paper Fig. 3).
    Fig3,
    /// Select, d = 3, 4, 5, 6, 1.28 M steps, 3 seeds (paper Fig. 4).
    Fig4,
    /// The robot arm, 2.56 M steps (the paper does not say), 5 seeds (paper Fig. 5).
    Fig5,
}

impl Figure {
    /// (env, dims, steps, seeds) of the paper's grid.
    fn grid(self) -> (&'static str, Vec<usize>, u64, Vec<u64>) {
        match self {
            Self::Fig3 => ("angle", vec![2, 4, 8, 16], 2_560_000, vec![0, 1, 2]),
            Self::Fig4 => ("select", vec![3, 4, 5, 6], 1_280_000, vec![0, 1, 2]),
            Self::Fig5 => ("arm", vec![2], 2_560_000, vec![0, 1, 2, 3, 4]),
        }
    }

    fn name(self) -> &'static str {
        match self {
            Self::Fig3 => "fig3",
            Self::Fig4 => "fig4",
            Self::Fig5 => "fig5",
        }
    }
}

/// `saver repro` flags.
#[derive(Args, Clone, Debug)]
pub struct ReproArgs {
    /// The experiment.
    #[arg(value_enum)]
    pub figure: Figure,
    /// Folder of the grid's runs, figure and table (`<out>/<figure>/...`).
    #[arg(long, default_value = "results/repro")]
    pub out: PathBuf,
    /// Steps per run (default: the figure's).
    #[arg(long)]
    pub steps: Option<u64>,
    /// Seeds (default: the figure's).
    #[arg(long, value_delimiter = ',')]
    pub seeds: Option<Vec<u64>>,
    /// Dimensions (default: the figure's).
    #[arg(long, value_delimiter = ',')]
    pub dims: Option<Vec<usize>>,
    /// Runs at a time (each a process; SAVER's PCPN blocks use one thread each).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=256))]
    pub jobs: u32,
    /// Leave out SAVER with the paper's settings (whose PCPN takes the paper's 100,000
    /// pretraining batches on angle).
    #[arg(long)]
    pub no_faithful: bool,
    /// Folder of cached PCPNs.
    #[arg(long, default_value = "pcpn-cache")]
    pub pcpn_dir: PathBuf,
    /// PCPN pretraining batches for every SAVER variant (default: each variant's own;
    /// a smaller grid for a quick look).
    #[arg(long)]
    pub pretrain_batches: Option<u64>,
}

/// One run of the grid.
struct Cell {
    name: String,
    dir: PathBuf,
    args: Vec<String>,
}

fn cells(a: &ReproArgs, root: &Path) -> Vec<Cell> {
    let (env, dims, steps, seeds) = a.figure.grid();
    let dims = a.dims.clone().unwrap_or(dims);
    let seeds = a.seeds.clone().unwrap_or(seeds);
    let steps = a.steps.unwrap_or(steps);
    let mut variants = vec![
        ("saver", vec!["--algo", "saver"]),
        ("a2c", vec!["--algo", "a2c"]),
    ];
    if !a.no_faithful {
        variants.insert(1, ("saver-faithful", vec!["--algo", "saver", "--faithful"]));
    }
    let mut out = Vec::new();
    // The dimensions, then the seeds, outermost: every series gets its first seeds early.
    for &seed in &seeds {
        for &d in &dims {
            for (variant, flags) in &variants {
                let name = format!("{env}-d{d}-{variant}-seed{seed}");
                let dir = root.join(&name);
                let mut args: Vec<String> = vec!["train".into()];
                args.extend(flags.iter().map(|s| s.to_string()));
                for (k, v) in [
                    ("--env", env.to_string()),
                    ("--dim", d.to_string()),
                    ("--seed", seed.to_string()),
                    ("--steps", steps.to_string()),
                    ("--out", dir.display().to_string()),
                    ("--pcpn-dir", a.pcpn_dir.display().to_string()),
                ] {
                    args.extend([k.to_string(), v]);
                }
                if let (Some(n), true) = (a.pretrain_batches, variant.starts_with("saver")) {
                    args.extend(["--pretrain-batches".to_string(), n.to_string()]);
                }
                out.push(Cell { name, dir, args });
            }
        }
    }
    out
}

/// Steps a run folder's checkpoint holds (0 without one).
fn done_steps(dir: &Path) -> u64 {
    std::fs::File::open(dir.join(saver_learner::CHECKPOINT_FILE))
        .ok()
        .and_then(|f| saver_proto::read_metadata(std::io::BufReader::new(f)).ok())
        .and_then(|m| m.get("steps")?.parse().ok())
        .unwrap_or(0)
}

/// Runs `saver repro`.
pub fn run(a: ReproArgs) -> Result<()> {
    let root = a.out.join(a.figure.name());
    std::fs::create_dir_all(&root).with_context(|| format!("creating {}", root.display()))?;
    let steps = a.steps.unwrap_or(a.figure.grid().2);
    let all = cells(&a, &root);
    let (finished, todo): (Vec<&Cell>, Vec<&Cell>) =
        all.iter().partition(|c| done_steps(&c.dir) >= steps);
    eprintln!(
        "{}: {} runs in {} ({} finished already), {} at a time; logs in each run's train.log",
        a.figure.name(),
        all.len(),
        root.display(),
        finished.len(),
        a.jobs
    );
    let exe = std::env::current_exe().context("finding the saver binary")?;
    // The PCPNs first, one at a time (cached ones are found at once), so that runs in
    // parallel never pretrain the same one twice.
    for c in &todo {
        if c.args.iter().any(|x| x == "saver") {
            let mut p = vec!["pretrain".to_string()];
            let keep = ["--env", "--dim", "--pcpn-dir", "--pretrain-batches"];
            for w in c.args.windows(2) {
                if keep.contains(&w[0].as_str()) {
                    p.extend([w[0].clone(), w[1].clone()]);
                }
            }
            if c.args.iter().any(|x| x == "--faithful") {
                p.push("--faithful".into());
            }
            let status = Command::new(&exe)
                .args(&p)
                .stdout(Stdio::null())
                .status()
                .with_context(|| format!("pretraining the PCPN of {}", c.name))?;
            if !status.success() {
                bail!("pretraining the PCPN of {} failed ({status})", c.name);
            }
        }
    }
    let bar = ProgressBar::new(all.len() as u64);
    bar.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {pos}/{len} runs {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_position(finished.len() as u64);
    let mut queue = todo.into_iter();
    let mut running: Vec<(&Cell, Child)> = Vec::new();
    let mut failed = Vec::new();
    loop {
        while running.len() < a.jobs as usize {
            let Some(c) = queue.next() else { break };
            std::fs::create_dir_all(&c.dir)?;
            let log = std::fs::File::create(c.dir.join("train.log"))?;
            let child = Command::new(&exe)
                .args(&c.args)
                .env("SAVER_PCPN_THREADS", "1")
                .stdout(log.try_clone()?)
                .stderr(log)
                .stdin(Stdio::null())
                .spawn()
                .with_context(|| format!("starting {}", c.name))?;
            running.push((c, child));
        }
        if running.is_empty() {
            break;
        }
        let names: Vec<&str> = running.iter().map(|(c, _)| c.name.as_str()).collect();
        bar.set_message(format!("running: {}", names.join(", ")));
        std::thread::sleep(Duration::from_millis(500));
        let mut still = Vec::new();
        for (c, mut child) in running {
            match child.try_wait()? {
                None => still.push((c, child)),
                Some(status) => {
                    bar.inc(1);
                    if !status.success() {
                        bar.println(format!(
                            "{} failed ({status}); see {}",
                            c.name,
                            c.dir.join("train.log").display()
                        ));
                        failed.push(c.name.clone());
                    }
                }
            }
        }
        running = still;
    }
    bar.finish_with_message("done");
    let dirs: Vec<PathBuf> = all
        .iter()
        .filter(|c| c.dir.join("metrics.csv").exists() && c.dir.join("config.toml").exists())
        .map(|c| c.dir.clone())
        .collect();
    let groups = figures::group(&dirs)?;
    let at: Vec<u64> = [0.2, 0.5, 1.0]
        .iter()
        .map(|f| (steps as f64 * f) as u64)
        .collect();
    let table = figures::table(&groups, &at, 50.0);
    for ext in ["png", "svg"] {
        figures::draw(&groups, &root.join(format!("figure.{ext}")))?;
    }
    std::fs::write(root.join("table.md"), &table)?;
    crate::out!("{table}");
    crate::out!(
        "figure: {} (and .svg); table: {}",
        root.join("figure.png").display(),
        root.join("table.md").display()
    );
    if !failed.is_empty() {
        bail!("{} runs failed: {}", failed.len(), failed.join(", "));
    }
    Ok(())
}
