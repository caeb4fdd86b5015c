//! `arkit-tool clean`.

use arkit_core::atomic_file::{self, LockSupport};
use arkit_core::{Error, Result};
use arkit_tool::folder_state::human_bytes;
use clap::Args;
use serde_json::json;
use std::path::PathBuf;
use std::process::ExitCode;

/// Remove the temporaries that killed writers left in a folder (and its sub-folders).
///
/// A writer (convert, render, crops, augment, train, ...) writes each file under a
/// temporary name (`.NAME.tmp-TOKEN`) that it holds locked, and renames it when it is
/// complete. A writer killed on the way leaves its temporary behind, unlocked: that is
/// what `clean` removes. A temporary a running writer holds is left alone, whatever
/// machine of a shared folder it runs on, so `clean` is safe beside running writers.
/// Every writer does the same to its own output folder when it starts; `inspect`
/// lists the leftovers with their sizes.
///
/// Where the file system gives no working locks (some NFS mounts, Lustre without
/// `-o flock`), nothing can be told abandoned and `clean` refuses; --force removes
/// every temporary, for when you know no writer is running.
///
/// Example: arkit-tool clean data/arkit
///          arkit-tool clean data/arkit --dry-run --json
#[derive(Args, Debug)]
pub struct CleanArgs {
    /// The folder to clean (a dataset, a release, a model folder, ...).
    folder: PathBuf,
    /// List what would be removed, and remove nothing.
    #[arg(long)]
    dry_run: bool,
    /// Remove every temporary, held or not (only when no writer is running: for file
    /// systems without locks).
    #[arg(long)]
    force: bool,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: CleanArgs) -> Result<ExitCode> {
    if !a.folder.is_dir() {
        return Err(Error::invalid(
            a.folder.display().to_string(),
            "not a folder",
        ));
    }
    let support = atomic_file::lock_support(&a.folder);
    if let (LockSupport::Missing(why), false) = (&support, a.force) {
        return Err(Error::format(
            &a.folder,
            format!(
                "this file system gives no working locks ({why}), so a killed writer's temporary cannot be told from a running one's; rerun with --force when no writer is running"
            ),
        ));
    }
    let found = atomic_file::leftovers(&a.folder, true)?;
    let chosen = |abandoned: Option<bool>| a.force || abandoned == Some(true);
    let removed = if a.dry_run {
        Vec::new()
    } else if a.force {
        atomic_file::remove_all_temporaries(&a.folder, true)?
    } else {
        atomic_file::remove_stale_temporaries(&a.folder, true)?
    };
    let rel = |p: &std::path::Path| p.strip_prefix(&a.folder).unwrap_or(p).display().to_string();
    let freed: u64 = found
        .iter()
        .filter(|l| removed.contains(&l.path))
        .map(|l| l.bytes)
        .sum();
    if a.json {
        let items: Vec<_> = found
            .iter()
            .map(|l| {
                json!({
                    "path": rel(&l.path),
                    "bytes": l.bytes,
                    "abandoned": l.abandoned,
                    "removed": removed.contains(&l.path),
                })
            })
            .collect();
        let out = json!({
            "folder": a.folder.display().to_string(),
            "dry_run": a.dry_run,
            "locks": matches!(support, LockSupport::Working),
            "temporaries": items,
            "removed": removed.len(),
            "bytes_freed": freed,
        });
        println!("{}", serde_json::to_string_pretty(&out).unwrap_or_default());
        return Ok(ExitCode::SUCCESS);
    }
    if found.is_empty() {
        println!("{}: no temporaries", a.folder.display());
        return Ok(ExitCode::SUCCESS);
    }
    for l in &found {
        let verdict = if removed.contains(&l.path) {
            "removed"
        } else if a.dry_run && chosen(l.abandoned) {
            "would be removed"
        } else {
            match l.abandoned {
                Some(false) => "kept: a running writer holds it",
                Some(true) => "kept: it went before it could be removed",
                None => "kept: no locks to tell",
            }
        };
        println!("{} ({}): {verdict}", rel(&l.path), human_bytes(l.bytes));
    }
    println!(
        "{}: {} of {} temporaries removed, {} freed",
        a.folder.display(),
        removed.len(),
        found.len(),
        human_bytes(freed)
    );
    Ok(ExitCode::SUCCESS)
}
