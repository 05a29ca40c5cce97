//! `saver`: one binary for every role of the system. `saver train` runs everything in
//! one process (the embedded default); `saver pretrain` builds a PCPN; `saver bench`
//! measures the updates against the machine's matmul peak; `saver plot` draws curves.

use clap::{Parser, Subcommand};
use saver_run::{
    act, bench, clients, config, diagnose, eval, plot, pretrain, repro, services, train,
};
use std::process::ExitCode;

/// SAVER: state aligned vector rewards with quantile regression RL.
#[derive(Parser)]
#[command(name = "saver", version, about, propagate_version = true)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

// Parsed once per process: boxing the larger argument sets would buy nothing.
#[allow(clippy::large_enum_variant)]
#[derive(Subcommand)]
enum Command {
    /// Train in one process: PCPN (cached or pretrained), learner thread, actors.
    Train(config::TrainArgs),
    /// Pretrain a PCPN for an env and store it.
    Pretrain(pretrain::PretrainArgs),
    /// Time the updates and a rollout-plus-update cycle against the matmul peak.
    Bench(bench::BenchArgs),
    /// Run a trained policy on fresh episodes: success rate, lengths, returns, a picture.
    Eval(eval::EvalArgs),
    /// Act with a trained policy: observations (JSON lines) on stdin, actions on stdout.
    Act(act::ActArgs),
    /// Diagnostics: how well a PCPN's input gradient matches the env's true one.
    Diagnose(diagnose::DiagnoseArgs),
    /// Run one of the paper's experiments as a grid of runs, then its figure and table.
    Repro(repro::ReproArgs),
    /// Draw learning curves of run folders (seeds grouped) into a PNG or SVG, with a table.
    Plot(plot::PlotArgs),
    /// Serve the Learner gRPC service: batches rollouts from actors, updates, publishes.
    Learner(services::LearnerArgs),
    /// Act for a learner over gRPC: step envs with its newest weights, stream rollouts.
    Actor(services::ActorArgs),
    /// Serve the PcpnStore gRPC service: pretrain and hand out PCPNs.
    PcpnTrainer(services::PcpnTrainerArgs),
    /// Print a learner's current weights (version, tensor names and shapes); save them.
    Weights(clients::WeightsArgs),
    /// Print what a learner is doing: version, steps, registered actors, counters.
    Status(clients::StatusArgs),
    /// Exit 0 when a server answers SERVING on grpc.health.v1.
    Healthcheck(clients::HealthArgs),
}

/// Log filter unless RUST_LOG says otherwise.
const DEFAULT_LOG: &str =
    "warn,saver_core=info,saver_learner=info,saver_pcpn_trainer=info,saver_run=info";

/// `saver bench`'s log filter: its tables only, not the INFO lines of the services it
/// starts in-process (actors joining and leaving); RUST_LOG overrides.
const BENCH_LOG: &str = "warn";

fn main() -> ExitCode {
    let cli = Cli::parse();
    let default_log = match cli.command {
        Command::Bench(_) => BENCH_LOG,
        _ => DEFAULT_LOG,
    };
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                // Warnings, and what the services do (actors joining and leaving,
                // pretraining progress); RUST_LOG overrides.
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_log)),
        )
        .with_writer(std::io::stderr)
        .init();
    saver_run::init_process(None);
    let result = match cli.command {
        Command::Train(a) => train::run(a),
        Command::Pretrain(a) => pretrain::run(a),
        Command::Bench(a) => bench::run(a),
        Command::Eval(a) => eval::run(a),
        Command::Act(a) => act::run(a),
        Command::Diagnose(a) => diagnose::run(a),
        Command::Repro(a) => repro::run(a),
        Command::Plot(a) => plot::run(a),
        Command::Learner(a) => services::learner(a),
        Command::Actor(a) => services::actor(a),
        Command::PcpnTrainer(a) => services::pcpn_trainer(a),
        Command::Weights(a) => clients::weights(a),
        Command::Status(a) => clients::status(a),
        Command::Healthcheck(a) => clients::healthcheck(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
