//! Running the real `brickworld run` in tests: a small world on a free
//! loopback port, a guard that kills a daemon when a test panics, and the
//! requests the tests send.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use brickworld::engine::ctl::request;

use super::scratch::Scratch;

pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A small world's folder (removed when the guard is dropped, unless the
/// test fails), its config, its state directory and its control address.
pub fn setup(name: &str) -> (Scratch, PathBuf, PathBuf, String) {
    let scratch = Scratch::dir(&format!("daemon-{name}"));
    let dir = scratch.to_path_buf();
    let addr = format!("127.0.0.1:{}", free_port());
    let cfg = dir.join("world.toml");
    std::fs::write(
        &cfg,
        format!(
            "[world]\nsource = \"terrain\"\nsize = [48, 32, 48]\nseed = 3\n[sim]\ndt = 0.05\nscripts_dir = \"{}/scripts\"\n\
             [[scripts]]\nfile = \"water.lua\"\nparams = {{ rain = 0.2 }}\n[render]\nwidth = 32\nheight = 24\ntracer = \"cpu\"\naa = 2\nbeam = true\n\
             [frames]\nevery = 5\n[checkpoint]\nevery = 40\n[control]\naddr = \"{addr}\"\n",
            env!("CARGO_MANIFEST_DIR")
        ),
    )
    .unwrap();
    (scratch, cfg, dir.join("state"), addr)
}

/// A daemon that is killed if the test panics before stopping it
/// (regression: failed tests left daemons running and eating the CPU).
pub struct Daemon(pub Option<Child>);

impl std::ops::Deref for Daemon {
    type Target = Child;
    fn deref(&self) -> &Child {
        self.0.as_ref().expect("running")
    }
}

impl std::ops::DerefMut for Daemon {
    fn deref_mut(&mut self) -> &mut Child {
        self.0.as_mut().expect("running")
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        if let Some(mut c) = self.0.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// `brickworld VERB FILE --world CFG --state STATE` (`export` or
/// `import`), not yet run.
#[allow(dead_code)]
pub fn backup_cmd(
    verb: &str,
    file: impl AsRef<std::ffi::OsStr>,
    cfg: impl AsRef<Path>,
    state: impl AsRef<Path>,
) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_brickworld"));
    c.arg(verb)
        .arg(file)
        .arg("--world")
        .arg(cfg.as_ref())
        .arg("--state")
        .arg(state.as_ref());
    c
}

/// `brickworld run CFG --state STATE`, not yet started.
pub fn run_cmd(cfg: &Path, state: &Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_brickworld"));
    c.arg("run").arg(cfg).arg("--state").arg(state);
    c
}

/// Replace `from` (which must be there) by `to` in the world config.
pub fn edit_config(cfg: &Path, from: &str, to: &str) {
    let text = std::fs::read_to_string(cfg).unwrap();
    assert!(text.contains(from), "{from:?} is not in {text}");
    std::fs::write(cfg, text.replace(from, to)).unwrap();
}

/// Give the world of `setup` its own scripts directory (a copy of
/// `water.lua`) with one more script, `name`, whose source is `text`, run
/// after water.
#[allow(dead_code)]
pub fn add_script(cfg: &Path, name: &str, text: &str) {
    let scripts = cfg.parent().unwrap().join("scripts");
    std::fs::create_dir_all(&scripts).unwrap();
    std::fs::copy(
        concat!(env!("CARGO_MANIFEST_DIR"), "/scripts/water.lua"),
        scripts.join("water.lua"),
    )
    .unwrap();
    std::fs::write(scripts.join(name), text).unwrap();
    edit_config(
        cfg,
        concat!(env!("CARGO_MANIFEST_DIR"), "/scripts"),
        scripts.to_str().unwrap(),
    );
    edit_config(
        cfg,
        "[render]",
        &format!("[[scripts]]\nfile = \"{name}\"\n[render]"),
    );
}

/// The world of `setup` with the shipped `lava.lua` after water, the
/// shipped `materials.lua` beside it and a 2³ `lava_source` placed; its
/// (config, state, address, scripts directory).
#[allow(dead_code)]
pub fn lava_world(name: &str) -> (Scratch, PathBuf, PathBuf, String, PathBuf) {
    let (scratch, cfg, state, addr) = setup(name);
    add_script(&cfg, "lava.lua", &shipped_script("lava.lua"));
    let scripts = cfg.parent().unwrap().join("scripts");
    std::fs::write(
        scripts.join("materials.lua"),
        shipped_script("materials.lua"),
    )
    .unwrap();
    let mut text = std::fs::read_to_string(&cfg).unwrap();
    text.push_str("[[place]]\nmaterial = \"lava_source\"\nat = [20, 28, 20]\nsize = [2, 2, 2]\n");
    std::fs::write(&cfg, text).unwrap();
    (scratch, cfg, state, addr, scripts)
}

/// The text of a shipped script (`scripts/NAME`).
#[allow(dead_code)]
pub fn shipped_script(name: &str) -> String {
    std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("scripts")
            .join(name),
    )
    .unwrap()
}

pub fn start(cfg: &Path, state: &Path) -> Daemon {
    spawn(&mut run_cmd(cfg, state))
}

/// Start `cmd` (a [`run_cmd`] with more flags or environment) as a daemon:
/// stdout discarded, stderr kept for [`stop`].
pub fn spawn(cmd: &mut Command) -> Daemon {
    Daemon(Some(
        cmd.stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    ))
}

/// Whether an answer is the engine's 503 while it loads its world.
fn starting(code: u16, body: &str) -> bool {
    code == 503 && body.contains("the engine is starting")
}

/// `/status`, once the engine has loaded its world (until then it answers
/// 503, for up to 60 s).
pub fn status(addr: &str) -> serde_json::Value {
    let t = Instant::now();
    loop {
        let (code, body) = request(addr, "GET", "/status", None, "").unwrap();
        if starting(code, &body) && t.elapsed() < Duration::from_secs(60) {
            std::thread::sleep(Duration::from_millis(20));
            continue;
        }
        assert_eq!(code, 200, "{body}");
        return serde_json::from_str(&body).unwrap();
    }
}

/// The tick of a paused engine once no step is queued, after `before`
/// when given (a step asked for has run).
#[allow(dead_code)]
pub fn paused_tick(addr: &str, before: Option<u64>) -> u64 {
    wait_status(addr, "pausing", |s| {
        s["paused"] == true
            && s["steps_pending"] == 0
            && before.is_none_or(|t| s["tick"].as_u64() != Some(t))
    })["tick"]
        .as_u64()
        .unwrap()
}

/// `/status` once `ok` holds for it (polled every 20 ms); a panic naming
/// `what` after 60 s.
#[allow(dead_code)]
pub fn wait_status(
    addr: &str,
    what: &str,
    ok: impl Fn(&serde_json::Value) -> bool,
) -> serde_json::Value {
    let t = Instant::now();
    loop {
        let s = status(addr);
        if ok(&s) {
            return s;
        }
        assert!(t.elapsed() < Duration::from_secs(60), "{what}: {s}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

pub fn wait_ready(addr: &str) {
    let t = Instant::now();
    while t.elapsed() < Duration::from_secs(30) {
        // Ready once the engine reports its scripts (the server starts first).
        if let Ok((200, body)) = request(addr, "GET", "/status", None, "")
            && serde_json::from_str::<serde_json::Value>(&body)
                .is_ok_and(|s| s["scripts"].as_array().is_some_and(|a| !a.is_empty()))
        {
            return;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    panic!("the daemon did not answer within 30 s");
}

pub fn token(state: &Path) -> String {
    std::fs::read_to_string(state.join("control.token")).unwrap()
}

/// POST `body` to `path` with the token, once the engine has loaded its
/// world (until then it answers 503, for up to 60 s).
pub fn post(addr: &str, state: &Path, path: &str, body: &str) -> (u16, String) {
    let t = Instant::now();
    loop {
        let (code, reply) = request(addr, "POST", path, Some(&token(state)), body).unwrap();
        if starting(code, &reply) && t.elapsed() < Duration::from_secs(60) {
            std::thread::sleep(Duration::from_millis(20));
            continue;
        }
        return (code, reply);
    }
}

pub fn stop(mut daemon: Daemon) -> std::process::Output {
    // SIGTERM: the daemon checkpoints and exits cleanly.
    let _ = Command::new("kill")
        .arg("-TERM")
        .arg(daemon.id().to_string())
        .status();
    let t = Instant::now();
    while t.elapsed() < Duration::from_secs(30) {
        if daemon.try_wait().unwrap().is_some() {
            let child = daemon.0.take().expect("running");
            let out = child.wait_with_output().unwrap();
            super::cli::assert_no_panic(&String::from_utf8_lossy(&out.stderr), "the engine");
            return out;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    // Dropping `daemon` kills it.
    panic!("the daemon did not stop on SIGTERM");
}

/// The tick of the last commit in `state`'s world store (None: never
/// committed), read as a user's tools would, through the library.
#[allow(dead_code)]
pub fn stored_tick(cfg: &Path, state: &Path) -> Option<u64> {
    let identity = brickworld::engine::world_config::WorldConfig::load(cfg)
        .unwrap()
        .identity();
    let (db, _) = brickworld::persist::WorldDb::open(state, &identity).unwrap();
    let blob = db.state().unwrap()?;
    Some(brickworld::persist::state::decode(&blob).unwrap().tick)
}

/// The material registry and palette of `state`'s last commit, read as a
/// user's tools would, through the library: (id, name) by id, and the
/// colour of each id.
#[allow(dead_code)]
pub fn stored_materials(cfg: &Path, state: &Path) -> (Vec<(u8, String)>, Vec<[u8; 3]>) {
    let identity = brickworld::engine::world_config::WorldConfig::load(cfg)
        .unwrap()
        .identity();
    let (db, _) = brickworld::persist::WorldDb::open(state, &identity).unwrap();
    let st = brickworld::persist::state::decode(&db.state().unwrap().unwrap()).unwrap();
    (
        st.extras
            .materials
            .iter()
            .map(|m| (m.0, m.1.clone()))
            .collect(),
        (0..=255u8).map(|i| st.store.palette().rgb(i)).collect(),
    )
}

/// Run the daemon with `flag N` (`--ticks` or `--until-tick`), require
/// success; its (stdout, stderr).
#[allow(dead_code)]
pub fn run_ok(cfg: &Path, state: &Path, flag: &str, n: u64) -> (String, String) {
    let out = run_cmd(cfg, state)
        .arg(flag)
        .arg(n.to_string())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(out.status.success(), "{err}");
    super::cli::assert_no_panic(&err, "the engine");
    (String::from_utf8_lossy(&out.stdout).to_string(), err)
}

/// Run the daemon until the world reaches tick `end`; the world hash it
/// reports when it stops.
#[allow(dead_code)]
pub fn hash_at(cfg: &Path, state: &Path, end: u64) -> String {
    let (said, _) = run_ok(cfg, state, "--until-tick", end);
    let line = said
        .lines()
        .find(|l| l.starts_with(&format!("stopped at tick {end} ")))
        .unwrap_or_else(|| panic!("{said}"));
    line.split("world hash ")
        .nth(1)
        .unwrap()
        .trim_end_matches(')')
        .to_string()
}

/// Run the daemon for one tick, which must be refused in one line saying
/// `said` (`what` names the case in a failure); its output.
#[allow(dead_code)]
pub fn refused_start(cfg: &Path, state: &Path, what: &str, said: &str) -> std::process::Output {
    let out = run_cmd(cfg, state).args(["--ticks", "1"]).output().unwrap();
    super::cli::assert_clear_failure(&out, what, said);
    out
}

/// Run the daemon for `ticks` ticks, require success; its stderr.
#[allow(dead_code)]
pub fn stderr_of_ticks(cfg: &Path, state: &Path, ticks: u64) -> String {
    run_ok(cfg, state, "--ticks", ticks).1
}

/// The state (hex code) and socket inode of the server's end of the
/// loopback TCP connection between `server_port` (the daemon's) and
/// `client_port`, from `/proc/net/tcp` ("sl local rem st … inode", ports
/// in hex). None once the kernel has dropped it.
fn server_end(server_port: u16, client_port: u16) -> Option<(String, u64)> {
    let (local, remote) = (format!(":{server_port:04X}"), format!(":{client_port:04X}"));
    std::fs::read_to_string("/proc/net/tcp")
        .unwrap()
        .lines()
        .skip(1)
        .find_map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            (f.len() > 9 && f[1].ends_with(&local) && f[2].ends_with(&remote))
                .then(|| (f[3].to_string(), f[9].parse().unwrap_or(0)))
        })
}

/// Whether the server's end of the connection between `server_port` and
/// `client_port` is in one of `states` ("01" established, "08" waiting
/// for the server to close it).
#[allow(dead_code)]
pub fn server_end_in(server_port: u16, client_port: u16, states: &[&str]) -> bool {
    server_end(server_port, client_port).is_some_and(|(st, _)| states.contains(&st.as_str()))
}

/// The socket inode of the server's end of that connection, while the
/// kernel lists it.
#[allow(dead_code)]
pub fn server_end_inode(server_port: u16, client_port: u16) -> Option<u64> {
    server_end(server_port, client_port).map(|(_, inode)| inode)
}

/// Whether process `pid` holds a descriptor of socket `inode`: a server
/// has closed a connection only when this is false (the kernel may drop
/// the connection from its table earlier, once a reset comes back).
#[allow(dead_code)]
pub fn holds_socket(pid: u32, inode: u64) -> bool {
    let want = format!("socket:[{inode}]");
    std::fs::read_dir(format!("/proc/{pid}/fd")).is_ok_and(|d| {
        d.flatten()
            .any(|e| std::fs::read_link(e.path()).is_ok_and(|t| t.to_string_lossy() == want))
    })
}

/// `brickworld ctl --addr ADDR --state STATE ARGS…`, which must succeed
/// (it exits 0 once the engine applied the command).
pub fn ctl_ok(addr: &str, state: &Path, args: &[&str]) {
    let out = Command::new(env!("CARGO_BIN_EXE_brickworld"))
        .args(["ctl", "--addr", addr, "--state"])
        .arg(state)
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "ctl {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// `d`'s exit status once it has exited; a panic saying `what` after
/// `secs` seconds.
pub fn wait_for_exit(d: &mut Daemon, secs: u64, what: &str) -> std::process::ExitStatus {
    let t = Instant::now();
    loop {
        if let Some(s) = d.try_wait().unwrap() {
            return s;
        }
        assert!(t.elapsed() < Duration::from_secs(secs), "{what}");
        std::thread::sleep(Duration::from_millis(20));
    }
}
