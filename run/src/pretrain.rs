//! `saver pretrain` (a PCPN for an env and pretraining settings, into the store) and
//! the "which PCPN" step of a SAVER run, both over
//! [`saver_pcpn_trainer::obtain_pcpn`] with a progress display.

use crate::progress::Progress;
use anyhow::{Context, Result};
use clap::Args;
use saver_core::config::{PretrainConfig, RunConfig};
use saver_core::env::EnvSpec;
use saver_core::nets::Pcpn;
use saver_core::settings::{EnvSettings, PretrainSettings, RunSettings};
use saver_pcpn_trainer::{obtain_pcpn, Origin, PcpnInfo, PcpnStore};
use std::cell::RefCell;
use std::path::{Path, PathBuf};

/// `saver pretrain` flags: the env and the pretraining settings, nothing else.
#[derive(Args, Clone, Debug)]
pub struct PretrainArgs {
    /// The env.
    #[command(flatten)]
    pub env: EnvSettings,
    /// Pretraining settings.
    #[command(flatten)]
    pub pretrain: PretrainSettings,
    /// Start from the paper's pretraining settings (its number of batches).
    #[arg(long)]
    pub faithful: bool,
    /// Folder of the PCPN store.
    #[arg(long, value_name = "DIR", default_value = "pcpn-cache")]
    pub pcpn_dir: PathBuf,
}

impl PretrainArgs {
    /// The env spec and settings these flags ask for.
    pub fn resolve(&self) -> Result<(EnvSpec, PretrainConfig)> {
        Ok(RunSettings {
            env: self.env.clone(),
            pretrain: self.pretrain.clone(),
            faithful: self.faithful,
            ..Default::default()
        }
        .resolve_pretrain()?)
    }
}

/// Runs `saver pretrain`: the store's PCPN for these settings, pretrained if missing.
pub fn run(args: PretrainArgs) -> Result<()> {
    let (spec, p) = args.resolve()?;
    let store = PcpnStore::new(&args.pcpn_dir);
    let (_, info, origin) = obtain(&spec, &p, &store, None, None)?;
    if origin == Origin::Cached {
        crate::out!("The store already has this PCPN (same env and settings).");
    }
    print_info(&info);
    Ok(())
}

/// Prints what a PCPN is and where it lives.
pub fn print_info(info: &PcpnInfo) {
    let m = |k: &str| info.meta.get(k).cloned().unwrap_or_else(|| "?".into());
    crate::out!(
        "PCPN for {} in {}\n  pretrained {}\n  held-out quantile loss {} (untrained: {})\n  weights sha256 {}",
        info.spec,
        info.path.display(),
        info.pretrain,
        m("held_out_loss"),
        m("initial_held_out_loss"),
        info.weights_sha256
    );
}

/// [`obtain_pcpn`] with the waiting said on stderr and a progress bar.
fn obtain(
    spec: &EnvSpec,
    p: &PretrainConfig,
    store: &PcpnStore,
    explicit: Option<&Path>,
    pinned: Option<&str>,
) -> Result<(Pcpn, PcpnInfo, Origin)> {
    let progress: RefCell<Option<Progress>> = RefCell::new(None);
    let found = obtain_pcpn(
        spec,
        p,
        store,
        explicit,
        pinned,
        &mut |path| {
            eprintln!(
                "No PCPN for {spec} with these pretraining settings in the store: pretraining \
                 one ({} batches) into {}.",
                p.batches,
                path.display()
            );
            *progress.borrow_mut() = Some(Progress::new(
                &format!("pretrain {spec}"),
                p.batches,
                "batches",
            ));
        },
        &mut |b| {
            if let Some(bar) = progress.borrow_mut().as_mut() {
                bar.update(b.batch, &format!("loss {:.4}", b.loss));
            }
        },
    );
    if let Some(bar) = progress.borrow().as_ref() {
        bar.finish();
    }
    Ok(found?)
}

/// The PCPN of a SAVER run (none for A2C): `explicit` if given, else the store's for
/// the run's pretraining settings, else pretrained now; pinned to
/// `config.pcpn_sha256` when set (on resume: [`pin_saved`]). The choice is recorded
/// in `config` (weights sha256, and an explicit file's settings).
pub fn pcpn_for_run(
    config: &mut RunConfig,
    store: &PcpnStore,
    explicit: Option<&Path>,
) -> Result<Option<Pcpn>> {
    if !config.algo.has_pcpn() {
        return Ok(None);
    }
    let pinned = config.pcpn_sha256.clone();
    let (pcpn, info, origin) = obtain(
        &config.env,
        &config.pretrain,
        store,
        explicit,
        pinned.as_deref(),
    )
    .with_context(|| match explicit {
        Some(f) => format!("--pcpn {}", f.display()),
        None => format!("the PCPN store {}", store.dir().display()),
    })?;
    let how = match origin {
        Origin::Pretrained => None,
        Origin::Cached => Some("the cached PCPN"),
        Origin::File => Some("the PCPN file"),
    };
    match how {
        None => print_info(&info),
        Some(how) => eprintln!(
            "Using {how} {} (held-out loss {}, weights sha256 {}).",
            info.path.display(),
            info.meta.get("held_out_loss").map_or("?", String::as_str),
            &info.weights_sha256[..12]
        ),
    }
    record(config, &info)?;
    Ok(Some(pcpn))
}

/// Pins a resumed run to the PCPN its checkpoint used (`saved`, from
/// `check_settings`) unless its config names one already; every later check (the
/// store's, [`record`], the learner's start) then holds the PCPN to it.
pub fn pin_saved(config: &mut RunConfig, saved: Option<String>) {
    if config.pcpn_sha256.is_none() {
        config.pcpn_sha256 = saved;
    }
}

/// Records `info` as the run's PCPN; refused when the run is pinned to other weights.
pub fn record(config: &mut RunConfig, info: &PcpnInfo) -> Result<()> {
    if let Some(want) = config
        .pcpn_sha256
        .as_ref()
        .filter(|w| **w != info.weights_sha256)
    {
        anyhow::bail!(
            "{}: weights sha256 {}, but this run uses the PCPN {want}",
            info.path.display(),
            info.weights_sha256
        );
    }
    config.pretrain = info.pretrain;
    config.pcpn_sha256 = Some(info.weights_sha256.clone());
    Ok(())
}
