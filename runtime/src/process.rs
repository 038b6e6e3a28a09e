//! Facts about the running process that commands report, and the ties
//! between a supervisor and the node processes it starts.

/// Peak resident set size of this process so far (Linux `VmHWM`), or
/// `None` where the platform does not say.
pub fn peak_rss_bytes() -> Option<u64> {
    proc_kib("/proc/self/status", "VmHWM:").map(|kib| kib * 1024)
}

/// How much of this process's memory is in transparent huge pages
/// (`AnonHugePages` of `/proc/self/smaps_rollup`); `None` where the
/// kernel does not say.
pub fn huge_pages_bytes() -> Option<u64> {
    proc_kib("/proc/self/smaps_rollup", "AnonHugePages:").map(|kib| kib * 1024)
}

/// The kB figure on the line of `file` that starts with `key`.
fn proc_kib(file: &str, key: &str) -> Option<u64> {
    let text = std::fs::read_to_string(file).ok()?;
    let line = text.lines().find(|l| l.starts_with(key))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// Makes the process `cmd` starts die with this one, however this one
/// ends (SIGKILL included), so that no node outlives its supervisor.
pub fn die_with_parent(cmd: &mut tokio::process::Command) {
    #[cfg(target_os = "linux")]
    {
        let parent = std::process::id() as libc::pid_t;
        // A parent-death signal needs no code in the child and works on a
        // SIGKILLed parent; it follows the forking thread, which for
        // `dray cluster` is the one running the supervisor to its end.
        // SAFETY: only async-signal-safe calls between fork and exec.
        unsafe {
            cmd.pre_exec(move || {
                let sig = libc::SIGKILL as libc::c_ulong;
                if libc::prctl(libc::PR_SET_PDEATHSIG, sig, 0, 0, 0) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                // The parent died before the signal was asked for.
                if libc::getppid() != parent {
                    libc::_exit(1);
                }
                Ok(())
            });
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = cmd;
}

/// Sends SIGINT to process `pid`, as a terminal's Ctrl-C would (an error
/// where it is gone).
pub fn interrupt(pid: u32) -> std::io::Result<()> {
    #[cfg(unix)]
    {
        let pid = libc::pid_t::try_from(pid).map_err(std::io::Error::other)?;
        // SAFETY: kill has no memory effects.
        if unsafe { libc::kill(pid, libc::SIGINT) } != 0 {
            return Err(std::io::Error::last_os_error());
        }
        Ok(())
    }
    #[cfg(not(unix))]
    {
        let _ = pid;
        Err(std::io::Error::other("signals need a Unix"))
    }
}

/// How much lower than the rest of its process a render thread runs
/// (`nice` steps): rendering is the batch work of a host, and the
/// loader's fetches and decodes, the display's encoding and a viewer's
/// browser on the same host should not wait behind it.
pub const RENDER_THREAD_NICENESS: i32 = 5;

/// Lowers the calling thread's priority by `steps` nice levels (Linux
/// sets nice per thread); where it cannot, the thread runs as it is.
pub fn lower_this_thread_priority(steps: i32) {
    #[cfg(target_os = "linux")]
    // SAFETY: plain syscalls on the calling thread's own id.
    unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        *libc::__errno_location() = 0;
        let now = libc::getpriority(libc::PRIO_PROCESS, tid);
        if *libc::__errno_location() == 0 {
            let _ = libc::setpriority(libc::PRIO_PROCESS, tid, (now + steps).min(19));
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = steps;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn peak_rss_and_huge_pages_are_known_on_linux() {
        if cfg!(target_os = "linux") {
            let rss = super::peak_rss_bytes().expect("VmHWM");
            assert!(rss > 1 << 20, "{rss}");
            let huge = super::huge_pages_bytes().expect("AnonHugePages");
            assert!(huge <= rss, "{huge} of {rss}");
        }
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn a_thread_lowers_only_its_own_priority() {
        let nice = || unsafe {
            libc::getpriority(
                libc::PRIO_PROCESS,
                libc::syscall(libc::SYS_gettid) as libc::id_t,
            )
        };
        let here = nice();
        let there = std::thread::spawn(move || {
            let before = nice();
            lower_this_thread_priority(RENDER_THREAD_NICENESS);
            (before, nice())
        })
        .join()
        .unwrap();
        assert_eq!(there.1, (there.0 + RENDER_THREAD_NICENESS).min(19));
        assert_eq!(nice(), here, "the calling thread only");
    }
}
