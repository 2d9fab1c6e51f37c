//! The progress of every long command (CS3, `lcrl tune`, training,
//! evaluation): indicatif's bar at a terminal, and where stderr is a file
//! or a pipe (a log, CI, `| tee`) the same line written plainly: at once,
//! then at most every few seconds as the work moves, and the last one, so
//! a long command is never silent.

use std::io::{IsTerminal, Write};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle, TermLike};

/// How often a plain progress line is written.
pub const PLAIN_EVERY: Duration = Duration::from_secs(5);

/// A bar of `len` steps drawn with `template` (indicatif's syntax), on
/// stderr: a live bar at a terminal, plain lines otherwise.
pub fn bar(len: u64, template: &str) -> ProgressBar {
    let target = if std::io::stderr().is_terminal() { ProgressDrawTarget::stderr() } else { ProgressDrawTarget::term_like(Box::new(PlainLines::default())) };
    let bar = ProgressBar::with_draw_target(Some(len), target);
    if let Ok(style) = ProgressStyle::with_template(template) {
        bar.set_style(style.progress_chars("=> "));
    }
    // Drawn now, so the first line comes at once, not at the first step.
    bar.tick();
    bar
}

/// A terminal that keeps no cursor: each frame indicatif draws becomes one
/// line on stderr, the first at once and then at most one per
/// [`PLAIN_EVERY`].
#[derive(Debug, Default)]
struct PlainLines {
    /// When a line was last written, and whether a finished frame was.
    last: Mutex<(Option<Instant>, bool)>,
}

impl PlainLines {
    fn frame(&self, s: &str) -> std::io::Result<()> {
        let text = s.trim();
        if text.is_empty() {
            return Ok(());
        }
        let mut last = self.last.lock().unwrap_or_else(|p| p.into_inner());
        // The first frame of a finished bar (pos = len, "N/N") is written at
        // once, so a log ends on where the work ended; later ones (a bar
        // whose message still moves) only as often as any other.
        let finished = text.split_whitespace().any(|w| w.split_once('/').is_some_and(|(a, b)| !a.is_empty() && a == b));
        let first_finished = finished && !last.1;
        if last.0.is_some_and(|t| t.elapsed() < PLAIN_EVERY) && !first_finished {
            return Ok(());
        }
        *last = (Some(Instant::now()), last.1 || finished);
        writeln!(std::io::stderr(), "{text}")
    }
}

impl TermLike for PlainLines {
    fn width(&self) -> u16 {
        120
    }
    fn move_cursor_up(&self, _: usize) -> std::io::Result<()> {
        Ok(())
    }
    fn move_cursor_down(&self, _: usize) -> std::io::Result<()> {
        Ok(())
    }
    fn move_cursor_right(&self, _: usize) -> std::io::Result<()> {
        Ok(())
    }
    fn move_cursor_left(&self, _: usize) -> std::io::Result<()> {
        Ok(())
    }
    fn write_line(&self, s: &str) -> std::io::Result<()> {
        self.frame(s)
    }
    fn write_str(&self, s: &str) -> std::io::Result<()> {
        self.frame(s)
    }
    fn clear_line(&self) -> std::io::Result<()> {
        Ok(())
    }
    fn flush(&self) -> std::io::Result<()> {
        std::io::stderr().flush()
    }
}
