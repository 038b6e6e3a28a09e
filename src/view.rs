//! `dray view`: fly through a model in the browser. On a database it
//! writes a local cluster's config (one store, `--clients` clients, every
//! address a free loopback port, the camera framed on the model's bounds)
//! into a folder of its own, and runs it as `dray cluster` does; on a
//! config it runs that config, which must have a viewer and no camera path.
//! Either way the viewer's address is printed once every node has joined.

use anyhow::{bail, Context, Result};
use dray_scene::db::Database;
use dray_trace::camera::Camera;
use std::net::{SocketAddr, TcpListener, UdpSocket};
use std::path::{Path, PathBuf};

/// The viewer's address unless `--web` says otherwise (another free port
/// when it is taken).
pub const DEFAULT_WEB: &str = "127.0.0.1:7480";

/// What `dray view` was asked for.
pub struct ViewArgs {
    pub target: PathBuf,
    pub clients: u32,
    pub threads: usize,
    pub web: Option<String>,
    pub width: u32,
    pub height: u32,
}

/// Runs the view until Ctrl-C; the cluster's report.
pub fn view(a: &ViewArgs, exe: &Path) -> Result<dray_actors::supervisor::ClusterReport> {
    let (config_path, _workdir) = if a.target.is_dir() {
        let work = tempfile::Builder::new()
            .prefix("dray-view-")
            .tempdir()
            .context("making a folder for the view's config and certificates")?;
        let path = write_config(a, work.path())?;
        (path, Some(work))
    } else {
        (a.target.clone(), None)
    };
    let cfg = dray_config::Config::load(&config_path)?;
    if cfg.display.web.is_none() {
        bail!(
            "{}: no display.web: `dray view` needs the viewer's address in the config",
            config_path.display()
        );
    }
    if cfg.render.camera_path.is_some() {
        bail!(
            "{}: render.camera_path makes the cluster follow a path; leave it out to fly \
             (`dray cluster` shows a path in the viewer)",
            config_path.display()
        );
    }
    dray_actors::nodes::preflight(&cfg, None)?;
    println!("Ctrl-C stops the view");
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    Ok(rt.block_on(dray_actors::supervisor::cluster(
        exe,
        &config_path,
        &cfg,
        &[],
    ))?)
}

/// Writes the cluster config of a view of the database `a.target` into
/// `dir` (its certificates go beside it); the config's path.
fn write_config(a: &ViewArgs, dir: &Path) -> Result<PathBuf> {
    dray_config::check_image_side("--width", a.width)?;
    dray_config::check_image_side("--height", a.height)?;
    if a.clients == 0 || a.clients > 256 {
        bail!("--clients: {} is not in 1..=256", a.clients);
    }
    if a.threads > 256 {
        bail!("--threads: {} is not in 0..=256", a.threads);
    }
    let db_path = std::path::absolute(&a.target).context("the database's path")?;
    let db = Database::open(&db_path)?;
    let cam = Camera::default_for(&db.manifest.model_bounds, a.width, a.height);
    let web = web_address(a.web.as_deref())?;
    let [scheduler, display, store] = free_udp_ports()?;
    let f = |v: glam::Vec3| format!("[{}, {}, {}]", v.x, v.y, v.z);
    let config = format!(
        r#"# Written by `dray view` for {db}.
[scene]
database = "{db}"

[render]
width = {w}
height = {h}
shadows = true
light_dir = [0.3, 1.0, 0.2]

[render.camera]
eye = {eye}
look = {look}
up = {up}
fov_y_deg = {fov}

[scheduler]
address = "127.0.0.1:{scheduler}"

[display]
address = "127.0.0.1:{display}"
web = "{web}"

[[stores]]
address = "127.0.0.1:{store}"

[clients]
count = {clients}
threads = {threads}
cache_mb = 512

[certs]
dir = "{certs}"
"#,
        db = toml_str(&db_path)?,
        w = a.width,
        h = a.height,
        eye = f(cam.eye),
        look = f(cam.look),
        up = f(cam.up),
        fov = cam.fov_degrees,
        clients = a.clients,
        threads = a.threads,
        certs = toml_str(&dir.join("certs"))?,
    );
    let path = dir.join("view.toml");
    std::fs::write(&path, config).with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

/// A path as a TOML basic string's contents.
fn toml_str(p: &Path) -> Result<String> {
    let s = p
        .to_str()
        .with_context(|| format!("{}: not UTF-8", p.display()))?;
    Ok(s.replace('\\', "\\\\").replace('"', "\\\""))
}

/// The viewer's address: `--web` as given (an error if it does not parse;
/// port 0 picks a free one), else [`DEFAULT_WEB`], or a free port when
/// that one is taken.
fn web_address(web: Option<&str>) -> Result<SocketAddr> {
    if let Some(w) = web {
        let addr: SocketAddr = w
            .parse()
            .map_err(|_| anyhow::anyhow!("--web: {w:?} is not IP:PORT"))?;
        if addr.port() != 0 {
            return Ok(addr);
        }
        // Port 0 asks for any free port; the config needs the real one.
        return TcpListener::bind(addr)
            .and_then(|l| l.local_addr())
            .with_context(|| format!("--web: no free port on {}", addr.ip()));
    }
    let default: SocketAddr = DEFAULT_WEB.parse().expect("a valid address");
    if TcpListener::bind(default).is_ok() {
        return Ok(default);
    }
    let free = TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .context("finding a free port for the viewer")?;
    println!("{DEFAULT_WEB} is taken: the viewer listens on {free}");
    Ok(free)
}

/// Three loopback UDP ports free now (QUIC listens on UDP), all held
/// until all are chosen so that they differ.
fn free_udp_ports() -> Result<[u16; 3]> {
    let socks: Vec<UdpSocket> = (0..3)
        .map(|_| UdpSocket::bind("127.0.0.1:0"))
        .collect::<std::io::Result<_>>()
        .context("finding free ports for the nodes")?;
    let mut ports = [0u16; 3];
    for (p, s) in ports.iter_mut().zip(&socks) {
        *p = s.local_addr().context("a free port")?.port();
    }
    Ok(ports)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_view_config_loads_and_frames_the_model() {
        let db = dray_testkit::plant_db(20_000, 1, 2048);
        let dir = tempfile::tempdir().unwrap();
        let a = ViewArgs {
            target: db.path.clone(),
            clients: 3,
            threads: 1,
            web: Some("127.0.0.1:0".into()),
            width: 320,
            height: 200,
        };
        let path = write_config(&a, dir.path()).unwrap();
        let cfg = dray_config::Config::load(&path).unwrap();
        assert_eq!(cfg.clients.count, 3);
        assert_eq!((cfg.render.width, cfg.render.height), (320, 200));
        assert!(cfg.render.camera_path.is_none() && cfg.display.web.is_some());
        let bounds = db.db.manifest.model_bounds;
        let cam = cfg.render.camera;
        let centre = (bounds.lo() + bounds.hi()) * 0.5;
        assert!((glam::Vec3::from(cam.look) - centre).length() < 1e-3 * bounds.diagonal());
        assert!(dray_actors::nodes::interactive(&cfg));
    }

    #[test]
    fn bad_flags_are_named() {
        let db = dray_testkit::plant_db(20_000, 1, 2048);
        let dir = tempfile::tempdir().unwrap();
        let mut a = ViewArgs {
            target: db.path.clone(),
            clients: 0,
            threads: 1,
            web: None,
            width: 320,
            height: 200,
        };
        let e = write_config(&a, dir.path()).unwrap_err().to_string();
        assert!(e.starts_with("--clients"), "{e}");
        a.clients = 1;
        a.web = Some("nowhere".into());
        let e = write_config(&a, dir.path()).unwrap_err().to_string();
        assert!(e.starts_with("--web"), "{e}");
        a.web = None;
        a.width = 100_000;
        let e = format!("{:#}", write_config(&a, dir.path()).unwrap_err());
        assert!(e.contains("--width"), "{e}");
    }
}
