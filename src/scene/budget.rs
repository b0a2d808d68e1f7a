//! Memory guards for scene input: every source is checked against the
//! memory it will need *before* anything is allocated, and refused with a
//! one-line error that says how much it would need and how much there is.
//!
//! - Files are read only if they are regular files within a size limit, and
//!   through a capped reader (a device such as `/dev/zero` reports size 0).
//! - A world's need is estimated from its size: the dense brick grid (4
//!   bytes per brick cell) plus [`BYTES_PER_COLUMN`] for each 8×8 column's
//!   surface bricks (measured: the 8192×256×8192 terrain peaked at 3.79 GB,
//!   about 3.6 KiB a column), per 256 voxels of height: a taller world's
//!   columns hold more stored bricks (a 1024×4096×8192 terrain, estimated
//!   at 768 MiB with one column cost whatever the height, needed over
//!   2.7 GB and aborted).
//! - What there is: the least of the memory the kernel reports available,
//!   the cgroup's limit less its usage, and the address-space limit.

use std::io::Read;
use std::path::Path;

use glam::IVec3;

use super::SceneError;

/// Estimated bytes per 8×8 column of a built world (surface bricks, their
/// materials, the store's index).
pub const BYTES_PER_COLUMN: u64 = 4 << 10;

/// Read a whole regular file of at most `max` bytes.
pub fn read_file(path: &Path, max: u64) -> Result<Vec<u8>, SceneError> {
    let meta = std::fs::metadata(path).map_err(|e| SceneError::io(path, e))?;
    if !meta.is_file() {
        return Err(SceneError::NotAFile {
            path: path.to_path_buf(),
        });
    }
    if meta.len() > max {
        return Err(SceneError::too_large(
            path,
            format!("{} bytes, over the {max}-byte limit", meta.len()),
        ));
    }
    let f = std::fs::File::open(path).map_err(|e| SceneError::io(path, e))?;
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    f.take(max + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| SceneError::io(path, e))?;
    if bytes.len() as u64 > max {
        return Err(SceneError::too_large(
            path,
            format!("grew past the {max}-byte limit while being read"),
        ));
    }
    Ok(bytes)
}

/// Estimated bytes to build a world of `size` voxels.
pub fn world_bytes(size: IVec3) -> u64 {
    let s = size.max(IVec3::ONE).as_u64vec3();
    let columns = s.x.div_ceil(8).saturating_mul(s.z.div_ceil(8));
    let per_column = BYTES_PER_COLUMN.saturating_mul(s.y.div_ceil(256));
    grid_bytes(size).saturating_add(columns.saturating_mul(per_column))
}

/// Bytes of the dense brick grid over a world of `size` voxels (4 a cell).
pub fn grid_bytes(size: IVec3) -> u64 {
    let s = size.max(IVec3::ONE).as_u64vec3();
    s.x.div_ceil(8)
        .saturating_mul(s.y.div_ceil(8))
        .saturating_mul(s.z.div_ceil(8))
        .saturating_mul(4)
}

/// Bytes this process may still allocate, as far as the OS says.
pub fn available_bytes() -> u64 {
    let mut avail = u64::MAX;
    if let Ok(m) = std::fs::read_to_string("/proc/meminfo")
        && let Some(kb) = m
            .lines()
            .find(|l| l.starts_with("MemAvailable:"))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse::<u64>().ok())
    {
        avail = avail.min(kb * 1024);
    }
    if let Ok(groups) = std::fs::read_to_string("/proc/self/cgroup")
        && let Some(room) = cgroup_room(Path::new("/sys/fs/cgroup"), &groups)
    {
        avail = avail.min(room);
    }
    if let Some(v) = address_space_limit() {
        // The address space also holds code and mappings: keep a margin.
        avail = avail.min(v.saturating_sub(256 << 20));
    }
    avail
}

/// What this process's memory cgroups leave it: at each level from its own
/// group up to the hierarchy's root, the limit less the usage, the least
/// of them; `None` without a limit. `groups` is `/proc/self/cgroup`, and
/// `root` where the hierarchies are mounted: v2 (`0::PATH`) at `root` or
/// `root/unified`, with `memory.max` and `memory.current`; v1's memory
/// controller (`N:...memory...:PATH`) at `root/memory`, with
/// `memory.limit_in_bytes` and `memory.usage_in_bytes`; usage less the
/// inactive page cache (`memory.stat`), which the kernel reclaims first
/// (regression, scale
/// probe: only `root/memory.max` was read, so a v1 limit or a v2 group
/// below the root was not seen, and a world that could not fit was built
/// until the OOM killer ended it).
fn cgroup_room(root: &Path, groups: &str) -> Option<u64> {
    let read_u64 = |p: &Path| {
        std::fs::read_to_string(p)
            .ok()
            .and_then(|s| s.trim().parse::<u64>().ok())
    };
    // The page cache's inactive part is reclaimed before the limit bites:
    // usage counts it, and in a container it fills usage up to the limit
    // (review: every start there was refused with "24 MiB available").
    let inactive = |dir: &Path, key: &str| {
        std::fs::read_to_string(dir.join("memory.stat"))
            .ok()?
            .lines()
            .find_map(|l| {
                l.strip_prefix(key)?
                    .strip_prefix(' ')?
                    .trim()
                    .parse::<u64>()
                    .ok()
            })
    };
    let mut room: Option<u64> = None;
    let mut walk = |mount: &Path, group: &str, limit: &str, usage: &str, cache: &str| {
        let mut dir = mount.join(group.trim_start_matches('/'));
        loop {
            if let (Some(max), Some(cur)) = (read_u64(&dir.join(limit)), read_u64(&dir.join(usage)))
            {
                let cur = cur.saturating_sub(inactive(&dir, cache).unwrap_or(0));
                let left = max.saturating_sub(cur);
                room = Some(room.map_or(left, |r| r.min(left)));
            }
            if dir == mount || !dir.pop() || !dir.starts_with(mount) {
                break;
            }
        }
    };
    for line in groups.lines() {
        let mut parts = line.splitn(3, ':');
        let (Some(_), Some(controllers), Some(group)) = (parts.next(), parts.next(), parts.next())
        else {
            continue;
        };
        if controllers.is_empty() {
            for mount in [root.to_path_buf(), root.join("unified")] {
                walk(
                    &mount,
                    group,
                    "memory.max",
                    "memory.current",
                    "inactive_file",
                );
            }
        } else if controllers.split(',').any(|c| c == "memory") {
            walk(
                &root.join("memory"),
                group,
                "memory.limit_in_bytes",
                "memory.usage_in_bytes",
                "total_inactive_file",
            );
        }
    }
    room
}

/// This process's address-space limit in bytes (`ulimit -v`), if set.
fn address_space_limit() -> Option<u64> {
    std::fs::read_to_string("/proc/self/limits")
        .ok()?
        .lines()
        .find(|l| l.starts_with("Max address space"))?
        .split_whitespace()
        .nth(3)?
        .parse()
        .ok()
}

/// Field `key` (`VmRSS:`, `VmSize:`) of `/proc/PID/status`, in KiB.
fn status_kb(pid: u32, key: &str) -> Option<u64> {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .ok()?
        .lines()
        .find(|l| l.starts_with(key))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}

/// Bytes this process may still allocate *now*: [`available_bytes`], and
/// under an address-space limit, what of it this process has not mapped
/// yet (its threads' stacks and libraries count).
pub fn headroom_bytes() -> u64 {
    let have = available_bytes();
    match address_space_limit() {
        Some(limit) => {
            let mapped = status_kb(std::process::id(), "VmSize:").unwrap_or(0) * 1024;
            have.min(limit.saturating_sub(mapped))
        }
        None => have,
    }
}

/// `budget`, lowered to the most this process can hold (what it holds
/// now and three quarters of what it may still allocate: tables grow by
/// doubling, the old beside the new), with a warning naming both when it
/// is lowered (regression, scale probe: a budget of 1 TiB on a machine of
/// a few GiB let a streamed world's cache grow until the process aborted).
pub fn within_reach(budget: u64) -> u64 {
    let most = rss_kb() * 1024 + headroom_bytes() / 4 * 3;
    if budget > most {
        crate::say!(
            "warning: the memory budget {} is more than this process can have ({}): it keeps to that",
            human(budget),
            human(most)
        );
        return most;
    }
    budget
}

/// Human-readable bytes.
pub fn human(b: u64) -> String {
    match b {
        b if b >= 1 << 40 => format!("{:.1} TiB", b as f64 / (1u64 << 40) as f64),
        b if b >= 1 << 30 => format!("{:.1} GiB", b as f64 / (1u64 << 30) as f64),
        // One decimal below 10 MiB: "needs 1 MiB, over the limit of 1 MiB"
        // read as a contradiction (docs walk) when it needed 1.1.
        b if b >= 10 << 20 => format!("{:.0} MiB", b as f64 / (1u64 << 20) as f64),
        b if b >= 1 << 20 => format!("{:.1} MiB", b as f64 / (1u64 << 20) as f64),
        b => format!("{:.0} KiB", b as f64 / 1024.0),
    }
}

/// Refuse a world of `size` (from `what`) that would not fit in memory.
pub fn check_world(what: &str, size: IVec3) -> Result<(), SceneError> {
    let need = world_bytes(size);
    let have = available_bytes();
    if need > have {
        return Err(SceneError::OutOfMemory {
            what: what.to_string(),
            msg: format!(
                "a {}x{}x{} world needs about {} to build; {} is available",
                size.x,
                size.y,
                size.z,
                human(need),
                human(have)
            ),
        });
    }
    Ok(())
}

/// Measured bytes a brick with per-voxel data costs once built (its mask,
/// packed materials, coarse levels and the store's entry, with the build's
/// transient copies): 280–300 on tall random heightmaps of 256² to 1024²,
/// with a margin.
pub const BYTES_PER_STORED_BRICK: u64 = 320;

/// Refuse a source (`what`) whose `bricks` bricks with per-voxel data, on
/// top of `base` bytes (its grid and other estimates), would not fit.
pub fn check_stored_bricks(what: &str, bricks: u64, base: u64) -> Result<(), SceneError> {
    let need = bricks
        .saturating_mul(BYTES_PER_STORED_BRICK)
        .saturating_add(base);
    // What is left now: the file, its voxel list and the sort order are
    // already mapped (regression, review).
    let have = headroom_bytes();
    if need > have {
        return Err(SceneError::OutOfMemory {
            what: what.to_string(),
            msg: format!(
                "its {bricks} bricks with voxels need about {} to build; {} is available",
                human(need),
                human(have)
            ),
        });
    }
    Ok(())
}

/// Bytes one rendered frame of `width`×`height` holds on the CPU: colour,
/// depth and the hit per pixel.
pub fn image_bytes(width: u32, height: u32) -> u64 {
    let per_pixel = 3 + 4 + std::mem::size_of::<Option<crate::trace::Hit>>() as u64;
    width as u64 * height as u64 * per_pixel
}

/// Refuse `copies` frames of `width`×`height` (for `what`) that would not
/// fit in memory, before rendering any.
pub fn check_images(what: &str, width: u32, height: u32, copies: u64) -> Result<(), SceneError> {
    let need = image_bytes(width, height).saturating_mul(copies);
    let have = available_bytes();
    if need > have / 10 * 9 {
        return Err(SceneError::OutOfMemory {
            what: what.to_string(),
            msg: format!(
                "{copies} frame(s) of {width}x{height} need about {} (colour, depth and hits); {} is available: make the image smaller",
                human(need),
                human(have)
            ),
        });
    }
    Ok(())
}

/// Resident memory of this process in KiB (Linux), 0 if unknown.
pub fn rss_kb() -> u64 {
    rss_kb_of(std::process::id())
}

/// The most resident memory this process has held since it started, in
/// KiB (Linux's `VmHWM`), 0 if unknown.
pub fn rss_peak_kb() -> u64 {
    status_kb(std::process::id(), "VmHWM:").unwrap_or(0)
}

/// Resident memory of process `pid` in KiB (Linux), 0 if unknown.
pub fn rss_kb_of(pid: u32) -> u64 {
    status_kb(pid, "VmRSS:").unwrap_or(0)
}

/// Threads (tasks) this user may still start under `ulimit -u`, if
/// limited: the limit counts every task of the user, this process's and
/// others'. `None` when unlimited, and for root, whom the kernel exempts.
pub fn threads_left() -> Option<u64> {
    #[cfg(target_os = "linux")]
    {
        use std::os::unix::fs::MetadataExt;
        let (soft, _) =
            nix::sys::resource::getrlimit(nix::sys::resource::Resource::RLIMIT_NPROC).ok()?;
        let uid = std::fs::metadata("/proc/self").ok()?.uid();
        if soft == nix::sys::resource::RLIM_INFINITY || uid == 0 {
            return None;
        }
        let tasks: u64 = std::fs::read_dir("/proc")
            .ok()?
            .flatten()
            .filter(|e| e.metadata().is_ok_and(|m| m.is_dir() && m.uid() == uid))
            .filter_map(|e| std::fs::read_dir(e.path().join("task")).ok())
            .map(|t| t.count() as u64)
            .sum();
        Some(soft.saturating_sub(tasks))
    }
    #[cfg(not(target_os = "linux"))]
    None
}

/// Address space the process may still map under `ulimit -v`, if limited.
pub fn address_space_left() -> Option<u64> {
    #[cfg(target_os = "linux")]
    {
        let (soft, _) =
            nix::sys::resource::getrlimit(nix::sys::resource::Resource::RLIMIT_AS).ok()?;
        if soft == nix::sys::resource::RLIM_INFINITY {
            return None;
        }
        let status = std::fs::read_to_string("/proc/self/status").ok()?;
        let kb: u64 = status
            .lines()
            .find_map(|l| l.strip_prefix("VmSize:"))?
            .trim()
            .trim_end_matches("kB")
            .trim()
            .parse()
            .ok()?;
        Some(soft.saturating_sub(kb * 1024))
    }
    #[cfg(not(target_os = "linux"))]
    None
}

#[cfg(test)]
mod tests {
    /// Sizes under 10 MiB keep a decimal, so that a need just over a
    /// limit never prints as equal to it (docs walk: "needs 1 MiB, over
    /// the limit of 1 MiB").
    #[test]
    fn sizes_just_over_a_mebibyte_are_not_rounded_to_it() {
        assert_eq!(super::human(1_153_434), "1.1 MiB");
        assert_eq!(super::human(1 << 20), "1.0 MiB");
        assert_eq!(super::human(486 << 20), "486 MiB");
        assert_eq!(super::human(3 << 29), "1.5 GiB");
        assert_eq!(super::human(2048), "2 KiB");
    }

    /// Regression (scale probe): a v1 memory limit, and a v2 limit on a
    /// group below the root, were not seen. Each level from the process's
    /// group up counts, and the tightest wins; "max" and v1's unlimited
    /// value leave the room as it is.
    #[test]
    fn cgroup_limits_of_v1_and_of_nested_v2_groups_are_seen() {
        let root = std::env::temp_dir().join(format!("bw-cgroup-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let put = |dir: &str, files: &[(&str, &str)]| {
            let d = root.join(dir);
            std::fs::create_dir_all(&d).unwrap();
            for (name, text) in files {
                std::fs::write(d.join(name), text).unwrap();
            }
        };
        let v1 = [
            ("memory.limit_in_bytes", "9223372036854771712\n"),
            ("memory.usage_in_bytes", "1000\n"),
        ];
        put("memory", &v1);
        put("memory/jobs", &v1);
        put(
            "memory/jobs/one",
            &[
                ("memory.limit_in_bytes", "2147483648\n"),
                ("memory.usage_in_bytes", "1073741824\n"),
            ],
        );
        let v1_groups = "9:name=systemd:/\n4:cpu,memory:/jobs/one\n0::/\n";
        assert_eq!(super::cgroup_room(&root, v1_groups), Some(1 << 30));
        // Inactive page cache counts as room (it is reclaimed first).
        put(
            "memory/jobs/one",
            &[("memory.stat", "cache 900\ntotal_inactive_file 1000\n")],
        );
        assert_eq!(super::cgroup_room(&root, v1_groups), Some((1 << 30) + 1000));
        std::fs::remove_file(root.join("memory/jobs/one/memory.stat")).unwrap();
        // v2: the parent's limit is the tighter one.
        put("a", &[("memory.max", "max\n"), ("memory.current", "5\n")]);
        put(
            "a/b",
            &[("memory.max", "3000\n"), ("memory.current", "1000\n")],
        );
        put(
            "a/b/c",
            &[("memory.max", "10000\n"), ("memory.current", "500\n")],
        );
        assert_eq!(super::cgroup_room(&root, "0::/a/b/c\n"), Some(2000));
        put(
            "a/b",
            &[("memory.stat", "active_file 7\ninactive_file 600\n")],
        );
        assert_eq!(super::cgroup_room(&root, "0::/a/b/c\n"), Some(2600));
        // No limit anywhere: nothing said.
        assert_eq!(super::cgroup_room(&root, "0::/a\n"), None);
        assert_eq!(super::cgroup_room(&root, "garbage\n"), None);
        let _ = std::fs::remove_dir_all(&root);
    }
}
