//! What a training run says while it runs: the progress bar, the status line
//! of an iteration and where its time went.

use indicatif::ProgressBar;

use super::metrics::{CollectTimes, IterationRow};
use crate::learn::UpdateTimes;

/// The bar of a run from iteration `start` to `end`.
pub(super) fn progress_bar(start: usize, end: usize) -> ProgressBar {
    let bar = crate::progress::bar(end as u64, "it {pos}/{len} {msg}");
    bar.set_position(start as u64);
    bar
}

/// Prints above the bar on a terminal, plainly otherwise (logs of background runs).
pub(super) fn log_line(bar: &ProgressBar, line: String) {
    if bar.is_hidden() {
        println!("{line}");
    } else {
        bar.println(line);
    }
}

/// " on each of N ranks" for N > 1.
pub(super) fn ranks_note(ranks: usize) -> String {
    match ranks {
        1 => String::new(),
        n => format!(" on each of {n} ranks"),
    }
}

/// The one-line summary of an iteration (the bar's message and the log).
pub(super) fn status_line(row: &IterationRow) -> String {
    let (stats, update) = (row.episodes, row.update);
    format!(
        "it {:>5} | {:>7.1} min | {:>6.0} steps/s | collect {:.2}s learn {:.2}s | return {:>7.3} | len {:>5.0} | track {:.3} | falls {:>3}/{:<3} | level {:.2} | risk {}/{} | lr {:.1e} (mean {:.1e}) | std {:.3} | value loss {:.4}",
        row.iteration,
        row.wall_s / 60.0,
        row.iteration_env_steps as f64 / (row.collect_s + row.learn_s),
        row.collect_s,
        row.learn_s,
        stats.mean_return,
        stats.mean_length_steps,
        stats.lin_tracking_score,
        stats.falls,
        stats.episodes,
        row.terrain_level,
        row.risk_fired.iter().sum::<u64>(),
        row.risk_exceeded.iter().sum::<u64>(),
        update.learning_rate,
        update.learning_rate_mean,
        update.mean_std,
        update.value_loss,
    )
}

/// One log line saying where the iteration's time went.
pub(super) fn time_split(c: &CollectTimes, l: &UpdateTimes) -> String {
    format!(
        "      time | collect: physics {:.3}s task {:.3}s reset {:.3}s inference {:.3}s storage {:.3}s | learn: targets {:.3}s gather {:.3}s forward {:.3}s loss {:.3}s backward {:.3}s clip {:.3}s adam {:.3}s comm {:.3}s",
        c.physics_s,
        c.task_s,
        c.reset_s,
        c.inference_s,
        c.storage_s,
        l.targets_s,
        l.gather_s,
        l.forward_s,
        l.loss_s,
        l.backward_s,
        l.clip_s,
        l.adam_s,
        l.comm_s
    )
}
