//! What the subcommands print while they work: progress bars and the samples they
//! skipped.

/// A progress bar for `len` items of `label` work (`{label} [=====>   ] 10/200 ...`).
pub(super) fn progress_bar(len: u64, label: &str, unit: &str) -> indicatif::ProgressBar {
    indicatif::ProgressBar::new(len).with_style(
        indicatif::ProgressStyle::with_template(&format!(
            "{{spinner}} {label} [{{bar:30}}] {{pos}}/{{len}} {unit} {{per_sec}} eta {{eta}}"
        ))
        .expect("valid progress template")
        .progress_chars("=> "),
    )
}

/// Prints, on stderr, how many samples a command could not read and why (the first
/// ten, each naming its file), so a moved release or a damaged image is never silent.
pub(super) fn report_unreadable(unreadable: &[(arkit_core::SampleKey, String)], command: &str) {
    if unreadable.is_empty() {
        return;
    }
    eprintln!(
        "{command}: skipped {} sample(s) whose image or annotation could not be read:",
        unreadable.len()
    );
    for (key, why) in unreadable.iter().take(10) {
        eprintln!("  {key}: {why}");
    }
    if unreadable.len() > 10 {
        eprintln!("  ... and {} more", unreadable.len() - 10);
    }
}
