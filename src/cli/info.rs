//! `arkit-tool info`.

use arkit_core::Result;
use arkit_core::release::read_info;
use clap::Args;
use serde_json::json;
use std::path::PathBuf;
use std::process::ExitCode;

/// Read and validate `_info.npz` annotations and print their pose.
///
/// Checks every array's shape and values (1220x3 finite `verts`, an orthonormal `R_t`
/// with tz < 0, ...). Exits 1 if any file is invalid, after reporting all of them.
///
/// Example: arkit-tool info data/ARKitFace_info_train/info/012345/01_Neutral/*_info.npz
#[derive(Args, Debug)]
pub struct InfoArgs {
    /// `_info.npz` files.
    #[arg(required = true)]
    files: Vec<PathBuf>,
    /// Print one JSON object per line.
    #[arg(long)]
    json: bool,
}

pub fn run(a: InfoArgs) -> Result<ExitCode> {
    let mut bad = 0;
    for path in &a.files {
        match read_info(path).and_then(|info| info.pose().map(|p| (info, p))) {
            Ok((info, pose)) => {
                let e = pose.euler();
                let t = pose.translation_m();
                if a.json {
                    println!(
                        "{}",
                        json!({"file": path, "ok": true, "yaw_deg": e.yaw_deg, "pitch_deg": e.pitch_deg, "roll_deg": e.roll_deg,
                               "translation_m": [t.x, t.y, t.z], "vertices": info.verts.len()})
                    );
                } else {
                    println!(
                        "{}: yaw {:.2} pitch {:.2} roll {:.2} deg, t = ({:.4}, {:.4}, {:.4}) m",
                        path.display(),
                        e.yaw_deg,
                        e.pitch_deg,
                        e.roll_deg,
                        t.x,
                        t.y,
                        t.z
                    );
                }
            }
            Err(err) => {
                bad += 1;
                if a.json {
                    println!(
                        "{}",
                        json!({"file": path, "ok": false, "error": err.to_string()})
                    );
                } else {
                    eprintln!("{err}");
                }
            }
        }
    }
    Ok(if bad == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}
