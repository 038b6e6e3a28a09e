//! Logging for every dray process: `tracing` with `RUST_LOG` honoured,
//! configured once.

use std::io::IsTerminal;
use std::sync::Once;
use tracing_subscriber::EnvFilter;

static INIT: Once = Once::new();

/// Installs the global subscriber: `RUST_LOG` when set, `default_filter`
/// otherwise; logs go to stderr so stdout stays for a command's output.
/// Colours only on a terminal (and not with `NO_COLOR` set), so that logs
/// redirected to a file or a pipe hold plain text. Calling it again does
/// nothing.
pub fn init(default_filter: &str) {
    INIT.call_once(|| {
        let filter =
            EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(default_filter));
        // Another subscriber set by a test harness is not an error.
        let _ = tracing_subscriber::fmt()
            .with_env_filter(filter)
            .with_writer(std::io::stderr)
            .with_ansi(colours())
            .try_init();
    });
}

/// Whether log lines get ANSI colours: stderr is a terminal and `NO_COLOR`
/// (<https://no-color.org>) is unset or empty.
fn colours() -> bool {
    let no_color = matches!(std::env::var_os("NO_COLOR"), Some(v) if !v.is_empty());
    std::io::stderr().is_terminal() && !no_color
}
