//! `saver train`'s flags: the run's settings (one definition with the config files,
//! [`saver_core::settings::RunSettings`]) and where its outputs and PCPN go.

use clap::Args;
use saver_core::settings::RunSettings;
use std::path::PathBuf;

/// `saver train` flags.
#[derive(Args, Clone, Debug)]
pub struct TrainArgs {
    /// The run's settings.
    #[command(flatten)]
    pub run: RunSettings,
    /// Run folder (default: runs/<env>-<algo>-seed<seed>-<unix time>).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Folder of cached PCPNs, one per env spec and pretraining settings.
    #[arg(long, value_name = "DIR", default_value = "pcpn-cache")]
    pub pcpn_dir: PathBuf,
    /// Use this PCPN file (refused if it was pretrained for another env spec); the run
    /// records its pretraining settings and weights sha256.
    #[arg(long, value_name = "FILE")]
    pub pcpn: Option<PathBuf>,
}
