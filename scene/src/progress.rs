//! Progress reporting for long commands: an indicatif bar with ETA when
//! stderr is a terminal, plain log lines every few seconds otherwise (CI
//! logs, pipes), nothing at all in tests.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::io::IsTerminal;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

const LOG_EVERY: Duration = Duration::from_secs(5);

enum Mode {
    Hidden,
    Bar(ProgressBar),
    Log,
}

/// A progress sink shared by every thread of a command.
pub struct Progress {
    mode: Mode,
    stage: Mutex<(String, Instant)>,
    total: AtomicU64,
    done: AtomicU64,
    cancelled: Arc<AtomicBool>,
}

impl Progress {
    /// A bar on a terminal, log lines otherwise.
    pub fn auto() -> Progress {
        let mode = if std::io::stderr().is_terminal() {
            let bar = ProgressBar::with_draw_target(Some(0), ProgressDrawTarget::stderr());
            bar.set_style(
                ProgressStyle::with_template(
                    "{msg:28} [{elapsed_precise}] {wide_bar} {human_pos}/{human_len} ({per_sec}, ETA {eta})",
                )
                .expect("valid template"),
            );
            Mode::Bar(bar)
        } else {
            Mode::Log
        };
        Self::with_mode(mode)
    }

    /// Reports nothing.
    pub fn hidden() -> Progress {
        Self::with_mode(Mode::Hidden)
    }

    fn with_mode(mode: Mode) -> Progress {
        Progress {
            mode,
            stage: Mutex::new((String::new(), Instant::now())),
            total: AtomicU64::new(0),
            done: AtomicU64::new(0),
            cancelled: Arc::new(AtomicBool::new(false)),
        }
    }

    /// Starts a new stage of `total` units.
    pub fn stage(&self, name: &str, total: u64) {
        self.total.store(total, Ordering::Relaxed);
        self.done.store(0, Ordering::Relaxed);
        match &self.mode {
            Mode::Hidden => {}
            Mode::Bar(bar) => {
                bar.set_message(name.to_string());
                bar.set_length(total);
                bar.set_position(0);
                bar.reset_eta();
            }
            Mode::Log => {
                tracing::info!("{name}: {total} to do");
                let mut stage = self.stage.lock().unwrap_or_else(|p| p.into_inner());
                *stage = (name.to_string(), Instant::now());
            }
        }
    }

    /// Marks `n` more units done.
    pub fn advance(&self, n: u64) {
        let done = self.done.fetch_add(n, Ordering::Relaxed) + n;
        match &self.mode {
            Mode::Hidden => {}
            Mode::Bar(bar) => {
                if done > bar.length().unwrap_or(0) {
                    bar.set_length(done);
                }
                bar.set_position(done);
            }
            Mode::Log => {
                // try_lock: a thread that finds the lock taken skips logging.
                if let Ok(mut stage) = self.stage.try_lock() {
                    if stage.1.elapsed() >= LOG_EVERY {
                        let total = self.total.load(Ordering::Relaxed).max(done);
                        tracing::info!(
                            "{}: {done}/{total} ({:.0} %)",
                            stage.0,
                            100.0 * done as f64 / total.max(1) as f64
                        );
                        stage.1 = Instant::now();
                    }
                }
            }
        }
    }

    /// A flag that, once set (say by a Ctrl-C handler), makes the long
    /// commands stop at their next check and clean up after themselves.
    pub fn cancel_flag(&self) -> Arc<AtomicBool> {
        self.cancelled.clone()
    }

    pub fn is_cancelled(&self) -> bool {
        self.cancelled.load(Ordering::Relaxed)
    }

    /// Clears the bar.
    pub fn finish(&self) {
        if let Mode::Bar(bar) = &self.mode {
            bar.finish_and_clear();
        }
    }
}
