//! The one look of rall's progress bars (training iterations, evaluation rollouts):
//! elapsed time, a 30-column bar, then what the bar counts.

use indicatif::{ProgressBar, ProgressStyle};

/// A bar of `len` steps drawn as `{elapsed} [=====>    ] <counts>`; `counts` is an
/// indicatif template fragment such as `"it {pos}/{len} {msg}"`.
pub fn bar(len: u64, counts: &str) -> ProgressBar {
    let bar = ProgressBar::new(len);
    bar.set_style(
        ProgressStyle::with_template(&format!("{{elapsed_precise}} [{{bar:30}}] {counts}"))
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    bar
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_bar_counts_what_it_is_given() {
        let b = bar(12, "{pos}/{len} rollouts");
        b.inc(5);
        assert_eq!((b.position(), b.length()), (5, Some(12)));
        // a template indicatif cannot read still gives a bar
        assert_eq!(bar(3, "{pos").length(), Some(3));
    }
}
