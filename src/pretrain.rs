//! `saver pretrain`: pretrain a PCPN for an env spec and write it to the store; also the
//! "cached or pretrained" step of `saver train`.

use crate::config::RunArgs;
use crate::progress::Progress;
use anyhow::{Context, Result};
use clap::Args;
use saver_core::config::RunConfig;
use saver_core::nets::Pcpn;
use saver_pcpn_trainer::{load_pcpn, pretrain_pcpn, PcpnInfo, PcpnStore};
use std::path::{Path, PathBuf};

/// `saver pretrain` flags.
#[derive(Args, Clone, Debug)]
pub struct PretrainArgs {
    /// The env to pretrain for, and pretraining settings (--pretrain-batches, --pretrain-lr).
    #[command(flatten)]
    pub run: RunArgs,
    /// Short for --pretrain-batches.
    #[arg(long, conflicts_with = "pretrain_batches")]
    pub batches: Option<u64>,
    /// Folder of the PCPN store.
    #[arg(long, value_name = "DIR", default_value = "pcpn-cache")]
    pub pcpn_dir: PathBuf,
    /// Retrain even if the store has a PCPN for this env.
    #[arg(long)]
    pub force: bool,
}

/// Runs `saver pretrain`.
pub fn run(args: PretrainArgs) -> Result<()> {
    let mut run = args.run.clone();
    if args.batches.is_some() {
        run.pretrain_batches = args.batches;
    }
    let config = run.resolve()?;
    let store = PcpnStore::new(&args.pcpn_dir);
    let dev = saver_core::device();
    if !args.force {
        if let Some((_, info)) = store.find(&config.env, &dev)? {
            println!(
                "A PCPN for {} is already in the store: {} (held-out loss {}); pass --force to retrain.",
                config.env,
                info.path.display(),
                info.meta.get("held_out_loss").map(String::as_str).unwrap_or("?")
            );
            return Ok(());
        }
    }
    let (_, info) = pretrain_and_store(&config, &store)?;
    print_info(&info);
    Ok(())
}

fn print_info(info: &PcpnInfo) {
    let m = |k: &str| info.meta.get(k).cloned().unwrap_or_else(|| "?".into());
    println!(
        "PCPN for {} written to {}\n  batches {} x {}, lr {}, seed {}\n  held-out quantile loss {} (untrained: {})\n  weights sha256 {}",
        info.spec,
        info.path.display(),
        m("batches"),
        m("batch_size"),
        m("lr"),
        m("seed"),
        m("held_out_loss"),
        m("initial_held_out_loss"),
        info.weights_sha256
    );
}

/// Pretrains with a progress display and saves into `store`.
pub fn pretrain_and_store(config: &RunConfig, store: &PcpnStore) -> Result<(Pcpn, PcpnInfo)> {
    let dev = saver_core::device();
    let mut progress = Progress::new(
        &format!("pretrain {}", config.env),
        config.pretrain.batches,
        "batches",
    );
    let report = pretrain_pcpn(config, &dev, &mut |p| {
        progress.update(p.batch, &format!("loss {:.4}", p.loss));
    })?;
    progress.finish();
    let info = store.save(&config.env, &report.tensors, report.meta)?;
    Ok((report.pcpn, info))
}

/// The PCPN for a run: `explicit` if given (refused for another env spec), else the
/// store's, else freshly pretrained into the store. Never retrains silently.
pub fn obtain_pcpn(
    config: &RunConfig,
    store: &PcpnStore,
    explicit: Option<&Path>,
) -> Result<(Pcpn, PcpnInfo)> {
    let dev = saver_core::device();
    if let Some(path) = explicit {
        return load_pcpn(path, &config.env, &dev)
            .with_context(|| format!("--pcpn {}", path.display()));
    }
    if let Some(found) = store.find(&config.env, &dev)? {
        eprintln!(
            "Using the cached PCPN {} (held-out loss {}).",
            found.1.path.display(),
            found
                .1
                .meta
                .get("held_out_loss")
                .map(String::as_str)
                .unwrap_or("?")
        );
        return Ok(found);
    }
    eprintln!(
        "No PCPN for {} in {}: pretraining one ({} batches).",
        config.env,
        store.path_for(&config.env).display(),
        config.pretrain.batches
    );
    let out = pretrain_and_store(config, store)?;
    print_info(&out.1);
    Ok(out)
}
