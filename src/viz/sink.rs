//! Where a recording goes: a file, a viewer we spawn, or a viewer already running.
//! Spawning and connecting fail fast, with what to install or start, instead of
//! logging into a buffer nobody reads.

use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::thread::JoinHandle;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use rerun::{RecordingStream, RecordingStreamBuilder, StoreId};

/// Viewer version that reads our recordings (the SDK's minor; the previous minor reads them too).
pub const VIEWER_PIP: &str = "pip install rerun-sdk==0.36.*";
/// Default viewer gRPC port (rerun's).
pub const DEFAULT_PORT: u16 = 9876;

/// Destination of a recording.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RerunTarget {
    /// Write an `.rrd` file (no viewer needed).
    Save(PathBuf),
    /// Start a `rerun` viewer from PATH (or reuse one listening on the default port).
    Spawn,
    /// Stream to a running viewer: `host:port` or a `rerun+http://host:port/proxy` URL.
    Connect(String),
}

impl RerunTarget {
    /// From the three mutually exclusive CLI options (at most one set).
    pub fn from_flags(
        save: Option<&Path>,
        spawn: bool,
        connect: Option<&str>,
    ) -> Option<RerunTarget> {
        match (save, spawn, connect) {
            (Some(p), _, _) => Some(RerunTarget::Save(p.to_path_buf())),
            (None, true, _) => Some(RerunTarget::Spawn),
            (None, false, Some(a)) => Some(RerunTarget::Connect(a.to_string())),
            (None, false, None) => None,
        }
    }
}

/// The gRPC proxy URL and the socket address of a `--connect` value.
pub fn parse_connect_addr(addr: &str) -> Result<(String, String)> {
    let addr = addr.trim();
    let hostport = if let Some(rest) = addr
        .strip_prefix("rerun+http://")
        .or_else(|| addr.strip_prefix("rerun+https://"))
    {
        rest.split('/').next().unwrap_or("").to_string()
    } else if addr.contains("://") {
        bail!("--connect takes host:port or rerun+http://host:port/proxy, not {addr:?}");
    } else if addr.is_empty() {
        format!("127.0.0.1:{DEFAULT_PORT}")
    } else if addr.contains(':') {
        addr.to_string()
    } else {
        format!("{addr}:{DEFAULT_PORT}")
    };
    let url = if addr.starts_with("rerun+") {
        addr.to_string()
    } else {
        format!("rerun+http://{hostport}/proxy")
    };
    Ok((url, hostport))
}

fn listening(hostport: &str) -> Result<Option<SocketAddr>> {
    let addrs: Vec<SocketAddr> = hostport
        .to_socket_addrs()
        .with_context(|| format!("cannot resolve viewer address {hostport:?}"))?
        .collect();
    Ok(addrs
        .into_iter()
        .find(|a| TcpStream::connect_timeout(a, Duration::from_millis(500)).is_ok()))
}

/// Whether an executable named `name` is on PATH.
pub fn on_path(name: &str) -> bool {
    std::env::var_os("PATH")
        .map(|p| std::env::split_paths(&p).any(|d| d.join(name).is_file()))
        .unwrap_or(false)
}

/// Opens a recording for `application_id` (the blueprint is tied to it) and sends
/// `blueprint` with it, so the viewer shows our layout.
pub fn open_recording(
    application_id: &'static str,
    recording_name: &str,
    target: &RerunTarget,
    layout: super::blueprint::Layout,
) -> Result<RecordingStream> {
    let builder = RecordingStreamBuilder::new(application_id).recording_name(recording_name);
    let rec = match target {
        RerunTarget::Save(path) => {
            if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
                std::fs::create_dir_all(dir)
                    .with_context(|| format!("creating {}", dir.display()))?;
            }
            builder
                .save(path)
                .with_context(|| format!("opening {} for the recording", path.display()))?
        }
        RerunTarget::Spawn => {
            let local = format!("127.0.0.1:{DEFAULT_PORT}");
            if listening(&local)?.is_none() && !on_path("rerun") {
                bail!(
                    "--spawn needs the rerun viewer: no `rerun` on PATH and nothing listening on {local}. \
                     Install it with `{VIEWER_PIP}` (then `rerun analytics disable`), or record to a file \
                     with --save FILE and open it later with `rerun FILE`"
                );
            }
            builder.spawn().context("spawning the rerun viewer")?
        }
        RerunTarget::Connect(addr) => {
            let (url, hostport) = parse_connect_addr(addr)?;
            if listening(&hostport)?.is_none() {
                bail!(
                    "--connect: nothing is listening at {hostport}. Start a viewer first (`rerun`, \
                     installed with `{VIEWER_PIP}`; it listens on port {DEFAULT_PORT}), or record to a \
                     file with --save FILE"
                );
            }
            builder
                .connect_grpc_opts(url)
                .with_context(|| format!("connecting to the viewer at {hostport}"))?
        }
    };
    send_layout_in_background(&rec, layout)?;
    Ok(rec)
}

/// Layouts being sent, by recording, until [`finish_recording`] joins them.
type PendingLayouts = Vec<(StoreId, JoinHandle<Result<()>>)>;
static PENDING_LAYOUTS: Mutex<PendingLayouts> = Mutex::new(Vec::new());

/// Builds and sends `layout` on its own thread: rerun needs about 2.5 ms to build a
/// blueprint (two in-memory streams), which `rall play` overlaps with building its
/// scene. The viewer keeps the blueprint store apart from the recording, so the
/// layout may arrive after the first data. [`finish_recording`] waits for it.
fn send_layout_in_background(
    rec: &RecordingStream,
    layout: super::blueprint::Layout,
) -> Result<()> {
    let id = store_id(rec).context("the recording has no store info")?;
    let sender = rec.clone();
    let handle = std::thread::Builder::new()
        .name("rall-layout".into())
        .spawn(move || layout.send(&sender))
        .context("starting the layout thread")?;
    let mut pending = PENDING_LAYOUTS.lock().unwrap_or_else(|e| e.into_inner());
    // Forget the finished sends of recordings that were dropped without finishing.
    pending.retain(|(_, h)| !h.is_finished());
    pending.push((id, handle));
    Ok(())
}

/// The recording's store (`None` for a disabled stream).
fn store_id(rec: &RecordingStream) -> Option<StoreId> {
    rec.store_info().map(|i| i.store_id)
}

/// Waits until the layout of `rec` (if one is being sent) is in the stream.
fn join_layout(rec: &RecordingStream) -> Result<()> {
    // A disabled stream has no store (and no layout).
    let Some(id) = store_id(rec) else {
        return Ok(());
    };
    let mine: Vec<_> = {
        let mut pending = PENDING_LAYOUTS.lock().unwrap_or_else(|e| e.into_inner());
        let (mine, rest) = std::mem::take(&mut *pending)
            .into_iter()
            .partition(|(i, _)| *i == id);
        *pending = rest;
        mine
    };
    for (_, h) in mine {
        h.join()
            .map_err(|_| anyhow::anyhow!("the layout thread panicked"))?
            .context("sending the viewer layout")?;
    }
    Ok(())
}

/// Flushes and closes a recording (a file gets its footer; a viewer gets everything).
pub fn finish_recording(rec: RecordingStream) -> Result<()> {
    join_layout(&rec)?;
    rec.flush_blocking().context("flushing the recording")?;
    rec.disconnect();
    drop(rec);
    Ok(())
}

/// Writes `blueprint` for `application_id` as an `.rbl` file.
pub fn write_blueprint_file(
    path: &Path,
    application_id: &'static str,
    layout: super::blueprint::Layout,
) -> Result<()> {
    let rec = rerun::RecordingStreamBuilder::new(application_id)
        .blueprint()
        .save(path)
        .with_context(|| format!("opening {}", path.display()))?;
    layout.send(&rec).context("writing the blueprint")?;
    finish_recording(rec)
}
