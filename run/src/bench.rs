//! `saver bench`: times the A2C and SAVER updates (B = 128, K = 32) for d = 2, 4, 8, 16
//! and a whole rollout-plus-update cycle, and puts each update's GFLOP/s beside the
//! single-core matmul GFLOP/s measured in the same run.
//!
//! FLOPs counted (multiply-add = 2): a trained dense layer costs 3× its forward
//! (forward, input gradient, weight gradient); the frozen PCPN costs 2× its forward
//! (forward and input gradient: no weight gradient is needed). QRRL's quantile policy
//! is trained, so its layers cost 3x, plus its embedding. Pretraining trains the
//! PCPN, so its layers cost 3× their forward, plus the cosine embedding and its product
//! with the chunks (one multiply each per row and feature).

use crate::train::train_with;
use anyhow::Result;
use candle_core::{Device, Tensor};
use clap::Args;
use saver_core::algo::{build, quantile_net_flops, threads_for, Algorithm, GradPath};
use saver_core::config::Algo;
use saver_core::config::PretrainConfig;
use saver_core::env::{EnvKind, EnvLayout, EnvSpec};
use saver_core::nets::Pcpn;
use saver_core::pretrain::{EnvSampler, Pretrainer};
use saver_core::rng::{rng_for, uniform01};
use saver_core::rollout::Batch;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// `saver bench` flags.
#[derive(Args, Clone, Debug)]
pub struct BenchArgs {
    /// Dimensions to time.
    #[arg(long, value_delimiter = ',', default_value = "2,4,8,16")]
    pub dims: Vec<usize>,
    /// Seconds to spend timing each update kind.
    #[arg(long, default_value_t = 2.0)]
    pub seconds: f64,
    /// Threads for SAVER's PCPN blocks in the whole-machine rows (default: one per
    /// core). The share-of-peak table always runs them on one thread.
    #[arg(long)]
    pub threads: Option<usize>,
    /// Updates in each rollout-plus-update cycle measurement.
    #[arg(long, default_value_t = 100)]
    pub cycle_updates: u64,
    /// Skip the gRPC service measurements.
    #[arg(long, conflicts_with = "services_only")]
    pub no_services: bool,
    /// Run only the gRPC service measurements.
    #[arg(long)]
    pub services_only: bool,
}

/// Calls `f` repeatedly for about `seconds` (after one warm-up call); mean seconds per call.
pub(crate) fn time<F: FnMut() -> Result<()>>(seconds: f64, mut f: F) -> Result<f64> {
    f()?;
    let start = Instant::now();
    let mut n = 0u32;
    while n < 3 || start.elapsed() < Duration::from_secs_f64(seconds) {
        f()?;
        n += 1;
    }
    Ok(start.elapsed().as_secs_f64() / n as f64)
}

/// Single-core f32 matmul GFLOP/s (1024³ through candle).
pub fn matmul_peak(seconds: f64) -> Result<f64> {
    let n = 1024;
    let dev = Device::Cpu;
    let mut rng = rng_for(1, 0);
    let a = Tensor::from_vec(uniform01(&mut rng, n * n), (n, n), &dev)?;
    let b = Tensor::from_vec(uniform01(&mut rng, n * n), (n, n), &dev)?;
    let s = time(seconds, || {
        a.matmul(&b)?;
        Ok(())
    })?;
    Ok(2.0 * (n * n * n) as f64 / s / 1e9)
}

use saver_core::algo::update_flops;

/// FLOPs of one pretraining batch of `b` samples with K = `k` (module doc).
pub fn pretrain_flops(l: &EnvLayout, b: usize, k: usize) -> f64 {
    let (pcpn, embed) = quantile_net_flops(b, k, l.pcpn_input_dim(), l.aligned_dim);
    3.0 * pcpn + 2.0 * embed
}

/// Seconds per pretraining batch on angle d with the default settings (batch 128,
/// K = 32; env sampling included), on `path` with the fused blocks on `threads`.
fn time_pretrain(d: usize, seconds: f64, path: GradPath, threads: usize) -> Result<(f64, f64)> {
    let spec = EnvSpec::new(EnvKind::Angle, d)?;
    let p = PretrainConfig::recommended(EnvKind::Angle);
    let source = Box::new(EnvSampler::new(&spec, 0, 1)?);
    let mut t = Pretrainer::new(source, &p, &Device::Cpu)?;
    t.set_grad_path(path);
    t.set_threads(threads);
    let s = time(seconds, || {
        t.step()?;
        Ok(())
    })?;
    Ok((s, pretrain_flops(&spec.layout(), p.batch_size, p.quantiles)))
}

/// The pretraining rows: batches/s and share of the matmul peak on one core, the
/// autograd reference beside it, and the blocks on `threads` threads.
fn pretraining(args: &BenchArgs, peak: f64, threads: usize) -> Result<()> {
    crate::out!(
        "\nPCPN pretraining (angle, batch 128, K = 32; hand-written path, blocks on 1 thread, \
         then on {threads}; candle autograd as the reference):"
    );
    crate::out!(
        "{:>3} {:>10} {:>10} {:>9} {:>12} {:>12} {:>13} {:>16}",
        "d",
        "batch/s",
        "GFLOP/s",
        "of peak",
        "autograd b/s",
        "vs autograd",
        format!("batch/s, {threads} thr"),
        "100k batches"
    );
    for &d in &args.dims {
        let (fast, flops) = time_pretrain(d, args.seconds, GradPath::Fast, 1)?;
        let (reference, _) = time_pretrain(d, args.seconds, GradPath::Reference, 1)?;
        let (wide, _) = time_pretrain(d, args.seconds, GradPath::Fast, threads)?;
        let gflops = flops / fast / 1e9;
        crate::out!(
            "{d:>3} {:>10.1} {:>10.2} {:>8.1}% {:>12.1} {:>11.2}x {:>13.1} {:>14.1} min",
            1.0 / fast,
            gflops,
            100.0 * gflops / peak,
            1.0 / reference,
            reference / fast,
            1.0 / wide,
            1e5 * wide / 60.0
        );
    }
    Ok(())
}

/// A batch of `t` trajectories × `n` steps with random contents of the right shapes.
pub(crate) fn synthetic_batch(l: &EnvLayout, t: usize, n: usize, seed: u64) -> Batch {
    let b = t * n;
    let mut rng = rng_for(seed, 9);
    let mut u = |len: usize| {
        uniform01(&mut rng, len)
            .into_iter()
            .map(|x| 2.0 * x - 1.0)
            .collect::<Vec<_>>()
    };
    Batch {
        n_traj: t,
        n_steps: n,
        obs: u(b * l.obs_dim),
        last_obs: u(t * l.obs_dim),
        actions: u(b * l.action_dim()),
        // A Gaussian payload: μ in (−1, 1), log σ = −1.
        payload: (0..b)
            .flat_map(|_| {
                let mu = u(l.mu_dim());
                mu.into_iter()
                    .chain(std::iter::repeat_n(-1.0, l.log_std_dim()))
            })
            .collect(),
        state_delta: u(b * l.aligned_dim).iter().map(|x| 0.1 * x).collect(),
        vector_reward: u(b * l.aligned_dim).iter().map(|x| 0.1 * x).collect(),
        env_reward: vec![],
        done: (0..b).map(|i| i % 97 == 0).collect(),
        timeouts: vec![],
        timeout_obs: vec![],
        steps: b as u64,
    }
}

/// Seconds per update of `algo` on angle d (a synthetic batch, a random PCPN; with
/// `tune`, SAVER's PCPN trained on each batch at a custom env's rate), with the
/// update's FLOPs and transitions.
fn time_update(
    algo: Algo,
    d: usize,
    seconds: f64,
    threads: usize,
    tune: bool,
    path: GradPath,
) -> Result<(f64, f64, usize)> {
    let dev = Device::Cpu;
    let spec = EnvSpec::new(EnvKind::Angle, d)?;
    let mut config = saver_core::algo::recommended(&spec, algo, 1);
    if tune {
        config.saver.pcpn_tune_lr = saver_core::algo::CUSTOM_SAVER_PCPN_TUNE_LR;
    }
    let pcpn = algo
        .has_pcpn()
        .then(|| Pcpn::random_frozen(&spec.layout(), 0, candle_core::DType::F32, &dev))
        .transpose()?;
    let mut a: Box<dyn Algorithm> = build(&config, pcpn, &dev)?;
    a.set_threads(threads);
    a.set_grad_path(path);
    // 16 actors x the rollout (PPO on angle: 128, 32 minibatches of 64 a pass).
    let batch = synthetic_batch(&spec.layout(), 16, config.rollout as usize, d as u64);
    let s = time(seconds, || {
        a.update(&batch)?;
        Ok(())
    })?;
    let flops = update_flops(&config, batch.len(), batch.n_traj);
    Ok((s, flops, batch.len()))
}

/// A table of an update's time at each d and its ratio to `base` (the same d's time in
/// the table above), headed `title`; `(algo, what)` name the row and the ratio's column.
fn ratio_table(
    title: &str,
    (algo, what): (&str, &str),
    dims: &[usize],
    base: &[f64],
    time: impl Fn(usize) -> Result<f64>,
) -> Result<()> {
    crate::out!("{title}");
    let head = format!("{what} / above");
    crate::out!("{:<6} {:>3} {:>12} {head:>16}", "algo", "d", "ms/update");
    for (&d, b) in dims.iter().zip(base) {
        let s = time(d)?;
        crate::out!("{algo:<6} {d:>3} {:>12.2} {:>15.2}x", s * 1e3, s / b);
    }
    Ok(())
}

/// Runs `saver bench`.
pub fn run(args: BenchArgs) -> Result<()> {
    if args.services_only {
        return services(&args);
    }
    // candle runs on RAYON_NUM_THREADS (1 unless set: see `init_process`).
    let peak = matmul_peak(args.seconds)?;
    crate::out!(
        "single-core matmul (1024^3, candle): {peak:.1} GFLOP/s; candle uses {} thread(s)\n",
        candle_core::utils::get_num_threads()
    );
    crate::out!(
        "updates on one core (B = 128, K = 32; PPO: B = 2048, 10 epochs of 32 minibatches \
         of 64; SAVER's PCPN blocks on 1 thread):"
    );
    crate::out!(
        "{:<6} {:>3} {:>12} {:>14} {:>10} {:>12}",
        "algo",
        "d",
        "ms/update",
        "steps/s",
        "GFLOP/s",
        "of peak"
    );
    let mut single = Vec::new();
    let mut ppo = Vec::new();
    for &algo in Algo::all() {
        for &d in &args.dims {
            let (s, flops, n) = time_update(algo, d, args.seconds, 1, false, GradPath::Fast)?;
            match algo {
                Algo::Saver => single.push(s),
                Algo::Ppo => ppo.push(s),
                _ => {}
            }
            let gflops = flops / s / 1e9;
            crate::out!(
                "{:<6} {d:>3} {:>12.2} {:>14.0} {:>10.2} {:>11.1}%",
                algo.name(),
                s * 1e3,
                n as f64 / s,
                gflops,
                100.0 * gflops / peak
            );
        }
    }
    ratio_table(
        "\nPPO's step through candle autograd (the reference of its hand-written path), one core:",
        ("ppo", "autograd"),
        &args.dims,
        &ppo,
        |d| Ok(time_update(Algo::Ppo, d, args.seconds, 1, false, GradPath::Reference)?.0),
    )?;
    ratio_table(
        "\nSAVER with its PCPN trained on each batch (--pcpn-tune-lr, a custom env's default), one core:",
        ("saver", "tuned"),
        &args.dims,
        &single,
        |d| Ok(time_update(Algo::Saver, d, args.seconds, 1, true, GradPath::Fast)?.0),
    )?;
    let threads = threads_for(args.threads.unwrap_or(crate::pcpn_threads()));
    if threads > 1 {
        crate::out!(
            "\nSAVER with its PCPN blocks and PPO with its critic's part on {threads} threads \
             (the default: one per core):"
        );
        crate::out!(
            "{:<6} {:>3} {:>12} {:>14} {:>14}",
            "algo",
            "d",
            "ms/update",
            "steps/s",
            "vs 1 thread"
        );
        for (algo, ones) in [(Algo::Saver, &single), (Algo::Ppo, &ppo)] {
            for (&d, one) in args.dims.iter().zip(ones) {
                let (s, _, n) = time_update(algo, d, args.seconds, threads, false, GradPath::Fast)?;
                crate::out!(
                    "{:<6} {d:>3} {:>12.2} {:>14.0} {:>13.2}x",
                    algo.name(),
                    s * 1e3,
                    n as f64 / s,
                    one / s
                );
            }
        }
    }
    crate::bench_custom::custom_env_updates(args.seconds)?;
    pretraining(&args, peak, threads)?;
    crate::out!("\nrollout + update cycle (16 actors x 8 steps, in-process, angle):");
    let dev = Device::Cpu;
    let out = std::env::temp_dir().join(format!("saver-bench-{}", std::process::id()));
    for (algo, d) in [(Algo::A2c, 4), (Algo::Saver, 4)] {
        let spec = EnvSpec::new(EnvKind::Angle, d)?;
        let mut config = saver_core::algo::recommended(&spec, algo, 0);
        config.steps = args.cycle_updates * config.batch_transitions();
        let pcpn = algo
            .has_pcpn()
            .then(|| Pcpn::random_frozen(&spec.layout(), 0, candle_core::DType::F32, &dev))
            .transpose()?;
        let run_dir = out.join(format!("{}-d{d}", algo.name()));
        let o = train_with(
            &config,
            &run_dir,
            pcpn,
            Arc::new(AtomicBool::new(false)),
            false,
        )?;
        crate::out!(
            "  {:<6} d={d}: {} updates in {:.2} s = {:.0} env steps/s ({:.2} ms per cycle)",
            algo.name(),
            o.version,
            o.wall_s,
            o.steps as f64 / o.wall_s,
            1e3 * o.wall_s / o.version as f64
        );
    }
    std::fs::remove_dir_all(&out).ok();
    if !args.no_services {
        services(&args)?;
    }
    Ok(())
}

fn services(args: &BenchArgs) -> Result<()> {
    use crate::bench_services::{broadcast_latency, ingress, processes_vs_embedded};
    crate::out!("\nservices (gRPC over loopback, angle d=4, sync mode):");
    for (algo, updates) in [
        (Algo::A2c, 4 * args.cycle_updates),
        (Algo::Saver, args.cycle_updates),
    ] {
        let (emb, bytes, files) = processes_vs_embedded(algo, updates)?;
        crate::out!(
            "  {}: 16 actor processes vs embedded: {bytes:.0} vs {emb:.0} env steps/s = {:.2} (goal >= 0.8)",
            algo.name(),
            bytes / emb
        );
        if let Some(files) = files {
            crate::out!(
                "  {}:   the same, weights read from the learner's files in /dev/shm: {files:.0} env steps/s = {:.2}",
                algo.name(),
                files / emb
            );
        }
    }
    let rate = ingress(args.seconds.max(2.0))?;
    crate::out!(
        "  learner ingress, no updates (A2C rollouts): {rate:.0} transitions/s = {:.2} of the 200k goal",
        rate / 200_000.0
    );
    let (p50, p99) = broadcast_latency(100)?;
    crate::out!(
        "  weight broadcast to 16 subscribers (A2C agent): p50 {p50:.2} ms, p99 {p99:.2} ms (goal p99 < 20 ms)"
    );
    Ok(())
}
