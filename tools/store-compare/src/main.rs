//! store-compare: redb vs SQLite (WAL) as the chunk store of brickworld.
//!
//! Usage:
//!   store-compare [KIND,KIND,...]      run everything (latency, size, reads, crash tests) and
//!                                      print Markdown tables; KIND = redb, redb-qr,
//!                                      sqlite-full, sqlite-normal (default: all four)
//!   store-compare crash-child KIND DIR (internal) loop committing generations until killed
//!
//! Any store error (e.g. "database disk image is malformed" after a kill) aborts the run
//! with a panic: that is a failure, not something to average away.
//!
//! Every store is used the same way: table `chunks` (12-byte key -> 32 KiB blob)
//! and table `meta` (key "state" -> blob), one write transaction per save, durable commit.

use rusqlite::OptionalExtension;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const CHUNK_BYTES: usize = 32 * 1024; // a compressed chunk (LZ4-ish, incompressible)
const STATE_BYTES: usize = 64 * 1024; // the per-save "world state" blob
const CRASH_CHUNKS: i32 = 50; // chunks rewritten per generation in the crash test
const CRASH_TRIALS: u64 = 20;

// ---------------------------------------------------------------- data helpers

/// Deterministic xorshift64 PRNG (no dependency, same numbers on every machine).
struct Rng(u64);
impl Rng {
    fn new(seed: u64) -> Self {
        Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
    }
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

/// `len` pseudo-random bytes; the first 8 bytes are `tag` (e.g. a generation number),
/// so a reader can check both "which write is this" and "is it torn".
fn payload(tag: u64, seed: u64, len: usize) -> Vec<u8> {
    let mut rng = Rng::new(seed ^ tag.rotate_left(32));
    let mut v: Vec<u8> = (0..len.div_ceil(8))
        .flat_map(|_| rng.next().to_le_bytes())
        .collect();
    v.truncate(len);
    v[..8].copy_from_slice(&tag.to_le_bytes());
    v
}

/// Chunk coordinate -> 12-byte key: big-endian with the sign bit flipped, so byte
/// order == numeric order (negative coordinates sort before positive ones).
fn chunk_key(x: i32, y: i32, z: i32) -> [u8; 12] {
    let mut k = [0u8; 12];
    for (i, c) in [x, y, z].into_iter().enumerate() {
        k[i * 4..i * 4 + 4].copy_from_slice(&((c as u32) ^ 0x8000_0000).to_be_bytes());
    }
    k
}

// ---------------------------------------------------------------- the two stores

#[derive(Clone, Copy, Debug)]
enum Kind {
    /// redb, default `Durability::Immediate`: fsync on commit, 1-phase commit + checksums.
    Redb,
    /// redb with `set_quick_repair(true)`: 2-phase commit (2 fsyncs) + allocator state saved
    /// in each commit, so reopening after a crash needs no full-file repair.
    RedbQr,
    /// SQLite, journal_mode=WAL, synchronous=FULL: the WAL is fsynced on every commit.
    SqliteFull,
    /// SQLite, journal_mode=WAL, synchronous=NORMAL: fsync only at checkpoints.
    SqliteNormal,
}
const KINDS: [Kind; 4] = [
    Kind::Redb,
    Kind::RedbQr,
    Kind::SqliteFull,
    Kind::SqliteNormal,
];

impl Kind {
    fn name(self) -> &'static str {
        match self {
            Kind::Redb => "redb",
            Kind::RedbQr => "redb-qr",
            Kind::SqliteFull => "sqlite-full",
            Kind::SqliteNormal => "sqlite-normal",
        }
    }
    fn parse(s: &str) -> Kind {
        *KINDS
            .iter()
            .find(|k| k.name() == s)
            .expect("unknown store kind")
    }
}

const CHUNKS: redb::TableDefinition<&[u8], &[u8]> = redb::TableDefinition::new("chunks");
const META: redb::TableDefinition<&str, &[u8]> = redb::TableDefinition::new("meta");

enum Store {
    Redb(redb::Database, bool /* quick_repair */),
    Sqlite(rusqlite::Connection),
}

impl Store {
    /// Open (creating if needed) the store in `dir`.
    fn open(kind: Kind, dir: &Path) -> Store {
        match kind {
            Kind::Redb | Kind::RedbQr => {
                let db = redb::Database::create(dir.join("world.redb")).unwrap();
                Store::Redb(db, matches!(kind, Kind::RedbQr))
            }
            Kind::SqliteFull | Kind::SqliteNormal => {
                let c = rusqlite::Connection::open(dir.join("world.sqlite")).unwrap();
                let sync = if matches!(kind, Kind::SqliteFull) {
                    "FULL"
                } else {
                    "NORMAL"
                };
                c.execute_batch(&format!(
                    "PRAGMA journal_mode=WAL; PRAGMA synchronous={sync};
                     CREATE TABLE IF NOT EXISTS chunks (k BLOB PRIMARY KEY, v BLOB NOT NULL);
                     CREATE TABLE IF NOT EXISTS meta (k TEXT PRIMARY KEY, v BLOB NOT NULL);"
                ))
                .unwrap();
                Store::Sqlite(c)
            }
        }
    }

    /// One write transaction: all `chunks` plus the state blob, committed durably.
    fn save(&mut self, chunks: &[([u8; 12], Vec<u8>)], state: &[u8]) {
        match self {
            Store::Redb(db, quick_repair) => {
                let mut tx = db.begin_write().unwrap(); // durability is Immediate (fsync) by default
                tx.set_quick_repair(*quick_repair);
                {
                    let mut t = tx.open_table(CHUNKS).unwrap();
                    for (k, v) in chunks {
                        t.insert(&k[..], &v[..]).unwrap();
                    }
                    tx.open_table(META).unwrap().insert("state", state).unwrap();
                }
                tx.commit().unwrap();
            }
            Store::Sqlite(c) => {
                let tx = c.transaction().unwrap();
                {
                    let mut put = tx
                        .prepare_cached("INSERT OR REPLACE INTO chunks VALUES (?1, ?2)")
                        .unwrap();
                    for (k, v) in chunks {
                        put.execute((&k[..], &v[..])).unwrap();
                    }
                    tx.execute("INSERT OR REPLACE INTO meta VALUES ('state', ?1)", [state])
                        .unwrap();
                }
                tx.commit().unwrap();
            }
        }
    }

    /// Read the state blob and the given chunks inside ONE read transaction (a consistent snapshot).
    fn load(&mut self, keys: &[[u8; 12]]) -> (Option<Vec<u8>>, Vec<Option<Vec<u8>>>) {
        match self {
            Store::Redb(db, _) => {
                use redb::ReadableDatabase;
                let tx = db.begin_read().unwrap();
                let state = match tx.open_table(META) {
                    Ok(t) => t.get("state").unwrap().map(|g| g.value().to_vec()),
                    Err(redb::TableError::TableDoesNotExist(_)) => {
                        return (None, vec![None; keys.len()])
                    }
                    Err(e) => panic!("{e}"),
                };
                let t = tx.open_table(CHUNKS).unwrap();
                let chunks = keys
                    .iter()
                    .map(|k| t.get(&k[..]).unwrap().map(|g| g.value().to_vec()))
                    .collect();
                (state, chunks)
            }
            Store::Sqlite(c) => {
                let tx = c.transaction().unwrap(); // BEGIN (deferred) = snapshot on first read
                let state = tx
                    .query_row("SELECT v FROM meta WHERE k='state'", [], |r| r.get(0))
                    .optional()
                    .unwrap();
                let chunks = {
                    let mut get = tx
                        .prepare_cached("SELECT v FROM chunks WHERE k=?1")
                        .unwrap();
                    keys.iter()
                        .map(|k| get.query_row([&k[..]], |r| r.get(0)).optional().unwrap())
                        .collect()
                };
                tx.commit().unwrap();
                (state, chunks)
            }
        }
    }
}

/// Disk usage of `dir` as "apparent MB / allocated MB [file names]". Apparent = sum of file
/// lengths; allocated = blocks really used (redb grows its file with sparse `set_len`).
fn dir_usage(dir: &Path) -> String {
    use std::os::unix::fs::MetadataExt;
    let (mut len, mut alloc, mut names) = (0, 0, vec![]);
    for e in std::fs::read_dir(dir).unwrap() {
        let e = e.unwrap();
        let m = e.metadata().unwrap();
        len += m.len();
        alloc += m.blocks() * 512;
        names.push(e.file_name().to_string_lossy().into_owned());
    }
    names.sort();
    format!(
        "{:.1} / {:.1} {}",
        len as f64 / 1e6,
        alloc as f64 / 1e6,
        names.join(",")
    )
}

/// For redb: reopen, `compact()`, and report the usage afterwards.
fn usage_after_compact(kind: Kind, dir: &Path) -> String {
    match Store::open(kind, dir) {
        Store::Redb(mut db, _) => {
            db.compact().unwrap();
            drop(db);
            dir_usage(dir)
        }
        Store::Sqlite(_) => "n/a".into(),
    }
}

fn fresh_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("store-compare-{}-{tag}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

// ---------------------------------------------------------------- 1. commit latency

fn bench_commit(kind: Kind) {
    let dir = fresh_dir(&format!("lat-{}", kind.name()));
    let mut store = Store::open(kind, &dir);
    let state = payload(0, 7, STATE_BYTES);
    for (k, reps) in [(1, 20), (100, 5), (1000, 3)] {
        let mut times = vec![];
        for rep in 0..reps {
            // New chunk keys each repetition (freshly generated terrain being saved).
            let chunks: Vec<_> = (0..k)
                .map(|i| {
                    (
                        chunk_key(i, rep, k),
                        payload(rep as u64, i as u64, CHUNK_BYTES),
                    )
                })
                .collect();
            let t = Instant::now();
            store.save(&chunks, &state);
            times.push(t.elapsed());
        }
        times.sort();
        let (med, max) = (times[times.len() / 2], times[times.len() - 1]);
        println!(
            "| {} | K={k} | {reps} | {:.2} | {:.2} | {:.0} |",
            kind.name(),
            ms(med),
            ms(max),
            (k as f64 * CHUNK_BYTES as f64 + STATE_BYTES as f64) / 1e6 / med.as_secs_f64()
        );
    }
    drop(store);
    let _ = std::fs::remove_dir_all(&dir);
}

// ---------------------------------------------------------------- 2. on-disk size + 3. reads

/// Returns (size table row, read table row).
fn bench_read(kind: Kind) -> (String, String) {
    const N: i32 = 4000;
    let dir = fresh_dir(&format!("read-{}", kind.name()));
    let size_row;
    let mut keys: Vec<[u8; 12]> = (0..N)
        .map(|i| chunk_key(i % 20 - 10, i / 400 - 5, (i / 20) % 20 - 10))
        .collect();
    {
        let mut store = Store::open(kind, &dir);
        for batch in keys.chunks(1000) {
            let chunks: Vec<_> = batch
                .iter()
                .enumerate()
                .map(|(i, k)| (*k, payload(1, i as u64, CHUNK_BYTES)))
                .collect();
            store.save(&chunks, &payload(0, 7, STATE_BYTES));
        }
        let open = dir_usage(&dir);
        drop(store);
        size_row = format!(
            "| {} (32 KiB blobs, 131.1 MB payload) | {open} | {} |",
            kind.name(),
            dir_usage(&dir)
        );
    }
    // Shuffle (Fisher-Yates with the deterministic PRNG), reopen, read everything in one read tx.
    let mut rng = Rng::new(42);
    for i in (1..keys.len()).rev() {
        keys.swap(i, rng.below(i as u64 + 1) as usize);
    }
    let mut store = Store::open(kind, &dir);
    let t = Instant::now();
    let (_, got) = store.load(&keys);
    let el = t.elapsed().as_secs_f64();
    let bytes: usize = got
        .iter()
        .map(|v| v.as_ref().expect("chunk missing").len())
        .sum();
    assert_eq!(bytes, N as usize * CHUNK_BYTES);
    let read_row = format!(
        "| {} | {N} | {:.1} | {:.0} | {:.0} |",
        kind.name(),
        el * 1e3,
        bytes as f64 / 1e6 / el,
        N as f64 / el
    );
    drop(store);
    let size_row = format!("{size_row} {} |", usage_after_compact(kind, &dir));
    let _ = std::fs::remove_dir_all(&dir);
    (size_row, read_row)
}

/// Size with realistic *varying* blob sizes: 4000 chunks of 1..63 KiB (mean ~32 KiB), then for
/// redb also after `compact()`. Returns a size table row.
fn bench_size_varied(kind: Kind) -> String {
    let dir = fresh_dir(&format!("size-{}", kind.name()));
    let mut rng = Rng::new(5);
    let mut payload_bytes = 0;
    let mut store = Store::open(kind, &dir);
    for b in 0..4 {
        let chunks: Vec<_> = (0..1000)
            .map(|i| {
                let len = 1024 + rng.below(62 * 1024) as usize;
                payload_bytes += len;
                (chunk_key(i, b, 0), payload(1, i as u64, len))
            })
            .collect();
        store.save(&chunks, &payload(0, 7, STATE_BYTES));
    }
    let open = dir_usage(&dir);
    drop(store);
    let row = format!(
        "| {} (1-63 KiB blobs, {:.1} MB payload) | {open} | {} | {} |",
        kind.name(),
        payload_bytes as f64 / 1e6,
        dir_usage(&dir),
        usage_after_compact(kind, &dir)
    );
    let _ = std::fs::remove_dir_all(&dir);
    row
}

// ---------------------------------------------------------------- 4./5. crash safety (kill -9)

fn crash_keys() -> Vec<[u8; 12]> {
    (0..CRASH_CHUNKS).map(|i| chunk_key(i, 0, -i)).collect()
}

/// Child: commit generation 1, 2, 3, ... forever; print g only AFTER commit() returned.
fn crash_child(kind: Kind, dir: &Path) {
    let mut store = Store::open(kind, dir);
    let keys = crash_keys();
    let mut out = std::io::stdout().lock();
    for g in 1u64.. {
        let chunks: Vec<_> = keys
            .iter()
            .enumerate()
            .map(|(i, k)| (*k, payload(g, i as u64, CHUNK_BYTES)))
            .collect();
        store.save(&chunks, &payload(g, 999, STATE_BYTES));
        writeln!(out, "{g}").unwrap();
        out.flush().unwrap();
    }
}

/// Result of one kill -9 trial.
struct Trial {
    ok: bool,
    acked: u64,         // last generation the child printed (= commit() had returned)
    found: u64,         // generation found on disk after reopening
    clean_open_ms: f64, // open + first read of a cleanly closed store (only with prefill)
    crash_open_ms: f64, // open + first read after the kill (includes crash recovery)
}

/// Parent: optionally prefill `prefill` extra chunks (a bigger world, to see how recovery
/// time scales), spawn the child, SIGKILL it at a random moment, reopen and verify.
fn crash_trial(kind: Kind, trial: u64, rng: &mut Rng, prefill: i32) -> Trial {
    let dir = fresh_dir(&format!("crash-{}-{trial}", kind.name()));
    let timed_open = |dir: &Path| {
        let t = Instant::now();
        let mut store = Store::open(kind, dir);
        let snapshot = store.load(&crash_keys());
        (ms(t.elapsed()), store, snapshot)
    };
    let mut clean_open_ms = 0.0;
    if prefill > 0 {
        let mut store = Store::open(kind, &dir);
        for b in 0..prefill / 1000 {
            let chunks: Vec<_> = (0..1000)
                .map(|i| (chunk_key(i, 100 + b, 0), payload(0, i as u64, CHUNK_BYTES)))
                .collect();
            store.save(&chunks, &payload(0, 999, STATE_BYTES));
        }
        drop(store);
        clean_open_ms = timed_open(&dir).0;
    }
    let mut child = Command::new(std::env::current_exe().unwrap())
        .args(["crash-child", kind.name(), dir.to_str().unwrap()])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    // Reader thread: the last generation the child acknowledged as durably committed.
    let reader = std::thread::spawn(move || {
        BufReader::new(stdout)
            .lines()
            .map_while(Result::ok)
            .filter_map(|l| l.parse::<u64>().ok())
            .last()
            .unwrap_or(0)
    });
    std::thread::sleep(Duration::from_millis(50 + rng.below(351)));
    child.kill().unwrap(); // SIGKILL on Unix
    child.wait().unwrap();
    let acked = reader.join().unwrap();

    // Reopen (this runs the store's crash recovery) and read everything in one snapshot.
    let (crash_open_ms, store, (state, chunks)) = timed_open(&dir);
    let found = state
        .as_ref()
        .map_or(0, |s| u64::from_le_bytes(s[..8].try_into().unwrap()));
    let state_ok = state.map_or(found == 0, |s| s == payload(found, 999, STATE_BYTES));
    // Every chunk must be exactly the one written by generation `found` (no torn transaction).
    let chunks_ok = chunks.iter().enumerate().all(|(i, c)| match c {
        Some(c) => *c == payload(found, i as u64, CHUNK_BYTES),
        None => found == 0,
    });
    // No lost commit: found >= acked. (found may be acked+1: committed but killed before printing.)
    let ok = state_ok && chunks_ok && found >= acked && found <= acked + 1;
    drop(store);
    let _ = std::fs::remove_dir_all(&dir);
    Trial {
        ok,
        acked,
        found,
        clean_open_ms,
        crash_open_ms,
    }
}

// ---------------------------------------------------------------- main

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() == 4 && args[1] == "crash-child" {
        return crash_child(Kind::parse(&args[2]), Path::new(&args[3]));
    }
    let kinds: Vec<Kind> = match args.get(1) {
        Some(s) => s.split(',').map(Kind::parse).collect(),
        None => KINDS.to_vec(),
    };
    println!("temp dir: {}\n", std::env::temp_dir().display());

    println!("## 1. Commit latency (K x 32 KiB chunks + 64 KiB state, one durable tx)\n");
    println!(
        "| store | K | reps | median ms | max ms | MB/s (median) |\n|---|---|---|---|---|---|"
    );
    for &k in &kinds {
        bench_commit(k);
    }

    println!("\n## 2. On-disk size after writing 4000 chunks (4 txs of 1000)\n");
    println!(
        "Each cell: apparent MB (file lengths) / allocated MB (disk blocks), files present.\n"
    );
    println!("| store | while open | after close | redb: after compact() |\n|---|---|---|---|");
    let rows: Vec<_> = kinds.iter().map(|&k| bench_read(k)).collect();
    rows.iter().for_each(|r| println!("{}", r.0));
    kinds
        .iter()
        .for_each(|&k| println!("{}", bench_size_varied(k)));
    println!(
        "\n## 3. Random point reads of 4000 chunks, shuffled, one fresh read tx (warm OS cache)\n"
    );
    println!("| store | reads | total ms | MB/s | reads/s |\n|---|---|---|---|---|");
    rows.iter().for_each(|r| println!("{}", r.1));

    println!(
        "\n## 4. kill -9 crash test ({CRASH_TRIALS} trials, child killed 50-400 ms after spawn)\n"
    );
    println!(
        "| store | passed | acked gens per trial (found on disk if different) |\n|---|---|---|"
    );
    for &k in &kinds {
        let mut rng = Rng::new(1234);
        let mut passed = 0;
        let mut log = vec![];
        for trial in 0..CRASH_TRIALS {
            let t = crash_trial(k, trial, &mut rng, 0);
            passed += t.ok as u32;
            log.push(match (t.ok, t.found == t.acked) {
                (true, true) => format!("{}", t.acked),
                (true, false) => format!("{}({})", t.acked, t.found),
                (false, _) => format!("FAIL:{}/{}", t.acked, t.found),
            });
        }
        println!(
            "| {} | {passed}/{CRASH_TRIALS} | {} |",
            k.name(),
            log.join(" ")
        );
    }

    println!(
        "\n## 5. Reopen time after kill -9 with a 4000-chunk (131 MB payload) store, 3 trials\n"
    );
    println!("| store | passed | clean reopen+read ms | reopen+read after kill ms (each trial) |\n|---|---|---|---|");
    for &k in &kinds {
        let mut rng = Rng::new(99);
        let trials: Vec<Trial> = (0..3)
            .map(|i| crash_trial(k, 100 + i, &mut rng, 4000))
            .collect();
        let f = |v: Vec<f64>| {
            v.iter()
                .map(|x| format!("{x:.1}"))
                .collect::<Vec<_>>()
                .join(" / ")
        };
        println!(
            "| {} | {}/3 | {} | {} |",
            k.name(),
            trials.iter().filter(|t| t.ok).count(),
            f(trials.iter().map(|t| t.clean_open_ms).collect()),
            f(trials.iter().map(|t| t.crash_open_ms).collect())
        );
    }
}
