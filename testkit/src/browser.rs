//! A headless Chromium driven over WebDriver (Debian's `chromium` and
//! `chromium-driver`), for the web viewer's test and benchmark; and a
//! `dray view` process whose viewer it opens.
//!
//! [`Browser::start`] is `None` where Chromium or chromedriver is missing
//! (the caller skips, unless [`REQUIRE_ENV`] is set: then it panics).

use fantoccini::actions::{InputSource, KeyAction, KeyActions};
use fantoccini::{Client, ClientBuilder};
use serde_json::{json, Value};
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Set (to anything) where a missing browser must fail the test, as on CI.
pub const REQUIRE_ENV: &str = "DRAY_REQUIRE_CHROMIUM";

/// WebDriver's code of the Home key.
pub const HOME_KEY: char = '\u{E011}';

/// The browser and the chromedriver it runs under; both stop on drop.
pub struct Browser {
    pub client: Client,
    driver: Child,
}

fn find(env: &str, names: &[&str]) -> Option<PathBuf> {
    if let Some(p) = std::env::var_os(env) {
        return Some(PathBuf::from(p));
    }
    names
        .iter()
        .map(Path::new)
        .find(|p| p.exists())
        .map(Path::to_path_buf)
}

impl Browser {
    /// A fresh headless Chromium with a `width` × `height` window; `None`
    /// when Chromium or chromedriver is not installed (and [`REQUIRE_ENV`]
    /// is not set).
    pub async fn start(width: u32, height: u32) -> Option<Browser> {
        let chromium = find(
            "DRAY_CHROMIUM",
            &["/usr/bin/chromium", "/usr/bin/chromium-browser"],
        );
        let driver = find("DRAY_CHROMEDRIVER", &["/usr/bin/chromedriver"]);
        let (Some(chromium), Some(driver)) = (chromium, driver) else {
            if std::env::var_os(REQUIRE_ENV).is_some() {
                panic!("{REQUIRE_ENV} is set but chromium or chromedriver is missing (Debian: chromium chromium-driver)");
            }
            eprintln!("skipped: no chromium or chromedriver (Debian: chromium chromium-driver)");
            return None;
        };
        let port = free_tcp_port();
        let driver = Command::new(&driver)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("starting {}: {e}", driver.display()));
        let profile = tempfile::tempdir().expect("a profile directory");
        let mut caps = serde_json::Map::new();
        caps.insert(
            "goog:chromeOptions".into(),
            json!({
                "binary": chromium,
                "args": [
                    "--headless=new", "--no-sandbox", "--disable-gpu",
                    "--disable-dev-shm-usage", "--disable-quic", "--no-first-run",
                    "--disable-background-networking", "--disable-component-update",
                    "--disable-sync", "--disable-extensions",
                    format!("--window-size={width},{height}"),
                    format!("--user-data-dir={}", profile.keep().display()),
                ],
            }),
        );
        // fantoccini's connector needs a TLS provider even for http://.
        let _ = rustls::crypto::ring::default_provider().install_default();
        let url = format!("http://127.0.0.1:{port}");
        let deadline = Instant::now() + Duration::from_secs(30);
        let client = loop {
            match ClientBuilder::rustls()
                .expect("a TLS connector")
                .capabilities(caps.clone())
                .connect(&url)
                .await
            {
                Ok(c) => break c,
                Err(e) if Instant::now() > deadline => panic!("chromedriver on {url}: {e}"),
                Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
            }
        };
        Some(Browser { client, driver })
    }

    /// Runs `js` (a function body: `return …`) in the page.
    pub async fn eval(&self, js: &str) -> Value {
        self.client
            .execute(js, Vec::new())
            .await
            .unwrap_or_else(|e| panic!("running {js:?} in the page: {e}"))
    }

    /// Waits until `js` returns true; panics with `what` after `timeout`,
    /// showing what `show` returns then.
    pub async fn wait_for(&self, what: &str, js: &str, show: &str, timeout: Duration) {
        let deadline = Instant::now() + timeout;
        loop {
            if self.eval(js).await == Value::Bool(true) {
                return;
            }
            if Instant::now() > deadline {
                panic!(
                    "{what}: not within {timeout:?}; page: {}",
                    self.eval(show).await
                );
            }
            tokio::time::sleep(Duration::from_millis(25)).await;
        }
    }

    /// Holds the key `key` down for `ms` milliseconds, as a person would.
    pub async fn hold_key(&self, key: char, ms: u64) {
        let keys = KeyActions::new("keyboard".into())
            .then(KeyAction::Down { value: key })
            .then(KeyAction::Pause {
                duration: Duration::from_millis(ms),
            })
            .then(KeyAction::Up { value: key });
        self.client
            .perform_actions(keys)
            .await
            .unwrap_or_else(|e| panic!("pressing {key:?}: {e}"));
    }

    /// A short press of `key`.
    pub async fn press(&self, key: char) {
        self.hold_key(key, 10).await;
    }

    /// Chooses `file` in the page's file input with the id `id`.
    pub async fn choose_file(&self, id: &str, file: &Path) {
        let input = self
            .client
            .find(fantoccini::Locator::Id(id))
            .await
            .unwrap_or_else(|e| panic!("no #{id} in the page: {e}"));
        input
            .send_keys(&file.display().to_string())
            .await
            .unwrap_or_else(|e| panic!("choosing {} in #{id}: {e}", file.display()));
    }

    /// The page as a PNG.
    pub async fn screenshot(&self) -> Vec<u8> {
        self.client
            .screenshot()
            .await
            .unwrap_or_else(|e| panic!("a screenshot: {e}"))
    }

    /// Closes the browser and its driver.
    pub async fn close(mut self) {
        let _ = self.client.clone().close().await;
        let _ = self.driver.kill();
        let _ = self.driver.wait();
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.driver.kill();
    }
}

/// `dray view DB --clients N --web WEB --width W --height H`'s arguments.
pub fn view_args(db: &Path, clients: u32, web: &str, (width, height): (u32, u32)) -> Vec<String> {
    let db = db.display().to_string();
    [
        "view",
        &db,
        "--clients",
        &clients.to_string(),
        "--web",
        web,
        "--width",
        &width.to_string(),
        "--height",
        &height.to_string(),
    ]
    .map(String::from)
    .to_vec()
}

/// A loopback TCP port free now.
pub fn free_tcp_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port()
}

/// A `dray view` (or any dray command that prints `viewer: URL`) running
/// until dropped (then sent SIGINT, as Ctrl-C would, and waited for).
pub struct Viewer {
    pub child: Child,
    /// The page's address, token included.
    pub url: String,
    /// The command's output lines after the URL, as they come.
    pub lines: std::sync::mpsc::Receiver<String>,
}

impl Viewer {
    /// Starts `dray ARGS` and waits (up to `timeout`) for its `viewer:`
    /// line.
    pub fn start<S: AsRef<std::ffi::OsStr>>(dray: &Path, args: &[S], timeout: Duration) -> Viewer {
        let mut child = Command::new(dray)
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap_or_else(|e| panic!("starting {}: {e}", dray.display()));
        let out = child.stdout.take().expect("piped stdout");
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(out).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let deadline = Instant::now() + timeout;
        let mut seen = Vec::new();
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match rx.recv_timeout(left) {
                Ok(line) => {
                    if let Some(url) = line.strip_prefix("viewer: ") {
                        return Viewer {
                            child,
                            url: url.trim().to_string(),
                            lines: rx,
                        };
                    }
                    seen.push(line);
                }
                Err(_) => {
                    let _ = child.kill();
                    let _ = child.wait();
                    panic!(
                        "no viewer address within {timeout:?}; output:\n{}",
                        seen.join("\n")
                    );
                }
            }
        }
    }

    /// Sends SIGINT (Ctrl-C) and waits up to `timeout` for the exit.
    pub fn interrupt(&mut self, timeout: Duration) -> Option<std::process::ExitStatus> {
        // SAFETY: kill(2) on our own child's pid.
        unsafe {
            libc::kill(self.child.id() as libc::pid_t, libc::SIGINT);
        }
        let deadline = Instant::now() + timeout;
        while Instant::now() < deadline {
            if let Ok(Some(status)) = self.child.try_wait() {
                return Some(status);
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        None
    }
}

impl Drop for Viewer {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            if self.interrupt(Duration::from_secs(10)).is_none() {
                let _ = self.child.kill();
                let _ = self.child.wait();
            }
        }
    }
}
