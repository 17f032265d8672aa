//! Figures about this process and the machine it runs on (resident memory, CPU time, load),
//! read from Linux's `/proc`; `None` where the platform does not offer them.
//!
//! The run summary reports peak memory and the benchmarks time phases with them, so they live
//! below both.

/// Memory field `key` (VmRSS, VmHWM, VmSize) of /proc/self/status in bytes.
fn status_bytes(key: &str) -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with(key))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Peak resident memory of the process so far, bytes.
pub fn peak_rss_bytes() -> Option<u64> {
    status_bytes("VmHWM")
}

/// Current resident memory of the process, bytes.
pub fn current_rss_bytes() -> Option<u64> {
    status_bytes("VmRSS")
}

/// Resets VmHWM to the current RSS (Linux `clear_refs` 5) so a phase's own peak is visible;
/// false where the kernel refuses (the peak then includes earlier phases).
pub fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

/// CPU time (user + system, all threads) of this process so far, s, from /proc/self/stat
/// (fields 14–15, in clock ticks of 1/100 s, the Linux USER_HZ).
pub fn process_cpu_s() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // The command name may hold spaces; fields are counted after its closing parenthesis.
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let (utime, stime): (u64, u64) = (f.get(11)?.parse().ok()?, f.get(12)?.parse().ok()?);
    Some((utime + stime) as f64 / 100.0)
}

/// The machine's load averages over 1, 5 and 15 minutes, to judge how shared it was.
pub fn load_average() -> Option<[f64; 3]> {
    let s = std::fs::read_to_string("/proc/loadavg").ok()?;
    let mut it = s.split_whitespace().map(|x| x.parse::<f64>().ok());
    Some([it.next()??, it.next()??, it.next()??])
}

/// Memory this process may still take, bytes, and what said so: the smallest of the
/// kernel's MemAvailable, the room left under the process's cgroup limit (v2 `memory.max`,
/// v1 `memory.limit_in_bytes`), since a container's limit is what kills it first, and the
/// room left under its address-space limit (`ulimit -v`, the service's `ingest_memory_mib`),
/// past which every allocation fails.
pub fn available_memory() -> Option<(u64, &'static str)> {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok();
    let machine = meminfo.as_deref().and_then(|m| {
        let line = m.lines().find(|l| l.starts_with("MemAvailable:"))?;
        let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
        Some((kb * 1024, "MemAvailable in /proc/meminfo"))
    });
    let cgroup =
        cgroup_room("memory.max", "memory.current", "the cgroup's memory.max").or_else(|| {
            cgroup_room(
                "memory/memory.limit_in_bytes",
                "memory/memory.usage_in_bytes",
                "the cgroup's memory.limit_in_bytes",
            )
        });
    [machine, cgroup, address_space_room()]
        .into_iter()
        .flatten()
        .min_by_key(|(bytes, _)| *bytes)
}

/// The address-space limit (`RLIMIT_AS`, from /proc/self/limits) less what the process has
/// mapped already (VmSize); `None` when unlimited or unreadable.
fn address_space_room() -> Option<(u64, &'static str)> {
    let limits = std::fs::read_to_string("/proc/self/limits").ok()?;
    let line = limits
        .lines()
        .find(|l| l.starts_with("Max address space"))?;
    // "Max address space   <soft>   <hard>   bytes": the soft limit is the one enforced.
    let soft: u64 = line
        .trim_start_matches("Max address space")
        .split_whitespace()
        .next()?
        .parse()
        .ok()?;
    let mapped = status_bytes("VmSize").unwrap_or(0);
    Some((
        soft.saturating_sub(mapped),
        "the room under the address-space limit: ulimit -v, or the service's ingest_memory_mib",
    ))
}

/// Limit minus usage of the cgroup files under /sys/fs/cgroup; `None` when unlimited
/// ("max", or v1's near-2⁶³ "no limit") or absent.
fn cgroup_room(limit: &str, usage: &str, source: &'static str) -> Option<(u64, &'static str)> {
    let read = |name: &str| -> Option<u64> {
        std::fs::read_to_string(format!("/sys/fs/cgroup/{name}"))
            .ok()?
            .trim()
            .parse()
            .ok()
    };
    let limit = read(limit).filter(|&l| l < 1 << 60)?;
    Some((limit.saturating_sub(read(usage).unwrap_or(0)), source))
}

/// Hands the memory freed by worker threads back to the system: glibc keeps freed blocks in
/// each thread's arena, which a run would otherwise carry through its solves.
pub fn return_freed_memory() {
    #[cfg(all(feature = "service", target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only walks and releases glibc's own free lists.
    unsafe {
        libc::malloc_trim(0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn figures_are_plausible_on_linux() {
        if !std::path::Path::new("/proc/self/status").exists() {
            return;
        }
        let current = current_rss_bytes().expect("VmRSS");
        let peak = peak_rss_bytes().expect("VmHWM");
        assert!(
            current > 0 && peak >= current,
            "current {current}, peak {peak}"
        );
        assert!(process_cpu_s().expect("stat") >= 0.0);
        assert!(load_average().expect("loadavg").iter().all(|l| *l >= 0.0));
        let (available, source) = available_memory().expect("meminfo");
        assert!(
            available > 0 && !source.is_empty(),
            "{available} from {source}"
        );
    }
}
