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
    /// A further variant of the grid, `NAME=FLAGS` (`saver train` flags, e.g.
    /// `--variant "saver-lr3e-3=--algo saver --lr 0.003"`); repeatable.
    #[arg(long = "variant", value_parser = parse_variant)]
    pub variants: Vec<(String, Vec<String>)>,
    /// Leave out the built-in variants (only the `--variant`s run).
    #[arg(long)]
    pub only_variants: bool,
}

/// Flags a variant may not set: the grid sets them per run.
const GRID_FLAGS: [&str; 6] = ["--env", "--dim", "--seed", "--steps", "--out", "--pcpn-dir"];

/// Parses `NAME=FLAGS` of `--variant`.
fn parse_variant(s: &str) -> Result<(String, Vec<String>), String> {
    let (name, flags) = s
        .split_once('=')
        .ok_or_else(|| format!("--variant {s:?}: expected NAME=FLAGS"))?;
    let name = name.trim();
    if name.is_empty()
        || !name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
    {
        return Err(format!(
            "--variant {s:?}: the name must be letters, digits, '-', '_' or '.' (it names run folders)"
        ));
    }
    let flags: Vec<String> = flags.split_whitespace().map(str::to_string).collect();
    if !flags
        .iter()
        .any(|f| f == "--algo" || f.starts_with("--algo="))
    {
        return Err(format!("--variant {s:?}: its flags must name the --algo"));
    }
    if let Some(f) = flags
        .iter()
        .find(|f| GRID_FLAGS.contains(&f.split('=').next().unwrap_or(f)))
    {
        return Err(format!(
            "--variant {s:?}: {f} is set by the grid (use --dims, --seeds, --steps, --out, --pcpn-dir)"
        ));
    }
    Ok((name.to_string(), flags))
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
    let owned = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    let mut variants: Vec<(String, Vec<String>)> = Vec::new();
    if !a.only_variants {
        variants.push(("saver".into(), owned(&["--algo", "saver"])));
        if !a.no_faithful {
            variants.push((
                "saver-faithful".into(),
                owned(&["--algo", "saver", "--faithful"]),
            ));
        }
        variants.push(("a2c".into(), owned(&["--algo", "a2c"])));
    }
    variants.extend(a.variants.iter().cloned());
    let mut out = Vec::new();
    // The dimensions, then the seeds, outermost: every series gets its first seeds early.
    for &seed in &seeds {
        for &d in &dims {
            for (variant, flags) in &variants {
                let name = format!("{env}-d{d}-{variant}-seed{seed}");
                let dir = root.join(&name);
                let mut args: Vec<String> = vec!["train".into()];
                args.extend(flags.iter().cloned());
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
                let own_batches = flags
                    .iter()
                    .any(|f| f.starts_with("--pretrain-batches") || f.starts_with("--batches"));
                if let (Some(n), true, false) = (a.pretrain_batches, is_saver(&args), own_batches) {
                    args.extend(["--pretrain-batches".to_string(), n.to_string()]);
                }
                out.push(Cell { name, dir, args });
            }
        }
    }
    out
}

/// What made a figure: the command, the commit, the machine, and per group its runs
/// and the PCPN each SAVER run used (weights sha256 and pretraining settings, from its
/// config.toml).
fn manifest(groups: &[figures::Group]) -> String {
    let quote = |a: String| {
        if a.chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_.,/=:".contains(c))
        {
            a
        } else {
            format!("'{}'", a.replace('\'', r"'\''"))
        }
    };
    let command: Vec<String> = std::env::args().skip(1).map(quote).collect();
    let commit = Command::new("git")
        .args(["rev-parse", "HEAD"])
        .stderr(Stdio::null())
        .output()
        .ok()
        .filter(|o| o.status.success())
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
        .unwrap_or_else(|| "none (not a git checkout)".into());
    let read = |f: &str, key: &str| {
        std::fs::read_to_string(f)
            .ok()
            .and_then(|t| t.lines().find(|l| l.starts_with(key)).map(str::to_string))
            .and_then(|l| Some(l.split_once(':')?.1.trim().to_string()))
    };
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    let mut out = format!(
        "# How this figure was made\n\n- command: `saver {}`\n- saver {}; git HEAD of the folder it ran from: {commit}\n- machine: {cores} logical CPUs ({}), {} memory\n\n## Groups\n\n",
        command.join(" "),
        env!("CARGO_PKG_VERSION"),
        read("/proc/cpuinfo", "model name").unwrap_or_else(|| "CPU unknown".into()),
        read("/proc/meminfo", "MemTotal").unwrap_or_else(|| "unknown".into()),
    );
    for g in groups {
        out += &format!("- **{}**: {} runs\n", g.label, g.runs.len());
        for r in &g.runs {
            let c = &r.config;
            let name = r
                .dir
                .file_name()
                .map_or(String::new(), |n| n.to_string_lossy().into());
            let pcpn = match &c.pcpn_sha256 {
                None => String::new(),
                Some(sha) => format!(": PCPN weights sha256 {sha} (pretrained {})", c.pretrain),
            };
            out += &format!("  - `{name}` (seed {}, {} steps){pcpn}\n", c.seed, c.steps);
        }
    }
    out
}

/// Whether `saver train` args run SAVER (which needs a PCPN).
fn is_saver(args: &[String]) -> bool {
    args.iter().any(|f| f == "--algo=saver")
        || args.windows(2).any(|w| w[0] == "--algo" && w[1] == "saver")
}

/// The `saver pretrain` args of a SAVER run's `saver train` args: its env, PCPN store,
/// `--faithful` and every `--pretrain-*` setting.
fn pretrain_args(train: &[String]) -> Vec<String> {
    let mut p = vec!["pretrain".to_string()];
    let mut i = 0;
    while i < train.len() {
        let f = &train[i];
        let key = f.split('=').next().unwrap_or(f);
        let keep = ["--env", "--dim", "--pcpn-dir", "--batches"].contains(&key)
            || key.starts_with("--pretrain-");
        if f == "--faithful" || (keep && f.contains('=')) {
            p.push(f.clone());
        } else if keep && i + 1 < train.len() {
            p.extend([f.clone(), train[i + 1].clone()]);
            i += 1;
        }
        i += 1;
    }
    p
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
    let mut names: Vec<&str> = all.iter().map(|c| c.name.as_str()).collect();
    names.sort_unstable();
    if let Some(w) = names.windows(2).find(|w| w[0] == w[1]) {
        bail!(
            "two variants would share the run folder {}: give each --variant its own name (built in: saver, saver-faithful, a2c)",
            w[0]
        );
    }
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
    // Each distinct PCPN once (the seeds of a series share theirs).
    let mut asked = std::collections::HashSet::new();
    for c in todo.iter().filter(|c| is_saver(&c.args)) {
        let p = pretrain_args(&c.args);
        if !asked.insert(p.clone()) {
            continue;
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
    std::fs::write(root.join("manifest.md"), manifest(&groups))?;
    crate::out!("{table}");
    crate::out!(
        "figure: {} (and .svg); table: {}; command, commit, machine and PCPNs: {}",
        root.join("figure.png").display(),
        root.join("table.md").display(),
        root.join("manifest.md").display()
    );
    if !failed.is_empty() {
        bail!("{} runs failed: {}", failed.len(), failed.join(", "));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn strings(s: &str) -> Vec<String> {
        s.split_whitespace().map(str::to_string).collect()
    }

    #[test]
    fn a_variant_is_a_name_and_train_flags_that_leave_the_grid_alone() {
        let (name, flags) = parse_variant("saver-lr3e-3=--algo saver --lr 0.003").unwrap();
        assert_eq!(name, "saver-lr3e-3");
        assert_eq!(flags, strings("--algo saver --lr 0.003"));
        for (bad, says) in [
            ("--algo saver", "NAME=FLAGS"),
            ("a/b=--algo saver", "the name must be"),
            ("=--algo saver", "the name must be"),
            ("x=--lr 0.003", "--algo"),
            ("x=--algo saver --dim 4", "--dim is set by the grid"),
            ("x=--algo saver --seed=3", "--seed=3 is set by the grid"),
        ] {
            let e = parse_variant(bad).unwrap_err();
            assert!(e.contains(says), "{bad}: {e}");
        }
    }

    #[test]
    fn pretraining_gets_the_runs_env_store_and_pretrain_settings_only() {
        let train = strings(
            "train --algo saver --faithful --pretrain-batches 100000 --pretrain-lr=0.002 --lr 0.003 \
             --env angle --dim 16 --seed 4 --steps 100 --out r/x --pcpn-dir p",
        );
        assert!(is_saver(&train));
        assert_eq!(
            pretrain_args(&train),
            strings(
                "pretrain --faithful --pretrain-batches 100000 --pretrain-lr=0.002 \
                 --env angle --dim 16 --pcpn-dir p"
            )
        );
        assert!(!is_saver(&strings("train --algo a2c --env angle")));
        assert!(is_saver(&strings("train --algo=saver")));
    }

    #[test]
    fn the_grid_takes_the_builtin_variants_then_the_users() {
        let a = ReproArgs {
            figure: Figure::Fig5,
            out: "o".into(),
            steps: Some(1000),
            seeds: Some(vec![7]),
            dims: None,
            jobs: 1,
            no_faithful: true,
            pcpn_dir: "p".into(),
            pretrain_batches: Some(50),
            variants: vec![parse_variant("fast=--algo saver --lr 0.003").unwrap()],
            only_variants: false,
        };
        let c = cells(&a, Path::new("o/fig5"));
        let names: Vec<&str> = c.iter().map(|c| c.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "arm-d2-saver-seed7",
                "arm-d2-a2c-seed7",
                "arm-d2-fast-seed7"
            ]
        );
        // --pretrain-batches goes to the SAVER variants only.
        let has_batches = |c: &Cell| c.args.iter().any(|f| f == "--pretrain-batches");
        assert_eq!(
            c.iter().map(has_batches).collect::<Vec<_>>(),
            [true, false, true]
        );
        assert_eq!(c[2].dir, Path::new("o/fig5/arm-d2-fast-seed7"));
        let only = cells(
            &ReproArgs {
                only_variants: true,
                ..a
            },
            Path::new("o"),
        );
        assert_eq!(only.len(), 1);
    }
}
