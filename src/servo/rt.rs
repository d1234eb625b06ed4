//! Real-time setup of the servo thread: SCHED_FIFO where permitted, optional CPU pinning, memory
//! locking and no timer slack. Anything refused becomes a warning and the loop runs anyway.

use thread_priority::{
    set_thread_priority_and_policy, thread_native_id, RealtimeThreadSchedulePolicy, ThreadPriority,
    ThreadSchedulePolicy,
};

use crate::config::ServoConfig;

/// What the servo thread got.
#[derive(Clone, Debug, Default)]
pub struct RealtimeSetup {
    pub fifo_priority: Option<u8>,
    pub pinned_cpu: Option<usize>,
    pub memory_locked: bool,
    /// One line per thing that was asked for and refused.
    pub warnings: Vec<String>,
}

/// Apply `config` to the calling thread (call it on the servo thread before the loop).
pub fn prepare_current_thread(config: &ServoConfig) -> RealtimeSetup {
    let mut setup = RealtimeSetup::default();
    // SAFETY: prctl with PR_SET_TIMERSLACK takes an integer argument and affects this thread only.
    unsafe { libc::prctl(libc::PR_SET_TIMERSLACK, 1 as libc::c_ulong, 0, 0, 0) };
    if config.lock_memory {
        // Lock pages as they are touched (MCL_ONFAULT), not every reserved mapping: the loop's
        // working set stays resident without charging allocator arenas to RLIMIT_MEMLOCK.
        // SAFETY: mlockall has no memory-safety preconditions.
        if unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE | libc::MCL_ONFAULT) } == 0
        {
            setup.memory_locked = true;
        } else {
            setup.warnings.push(format!(
                "cannot lock memory ({}); page faults may delay the loop (raise LimitMEMLOCK, see docs/install.md)",
                std::io::Error::last_os_error()
            ));
        }
    }
    if config.cpu >= 0 {
        let cpu = config.cpu as usize;
        // SAFETY: cpu_set_t is plain data; sched_setaffinity(0, ..) affects the calling thread.
        let ok = unsafe {
            let mut set: libc::cpu_set_t = std::mem::zeroed();
            libc::CPU_SET(cpu, &mut set);
            libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set) == 0
        };
        if ok {
            setup.pinned_cpu = Some(cpu);
        } else {
            setup.warnings.push(format!(
                "cannot pin the servo thread to CPU {cpu}: {}",
                std::io::Error::last_os_error()
            ));
        }
    }
    if config.realtime_priority > 0 {
        let priority = ThreadPriority::try_from(config.realtime_priority)
            .map_err(thread_priority::Error::Priority);
        let result = priority.and_then(|p| {
            set_thread_priority_and_policy(
                thread_native_id(),
                p,
                ThreadSchedulePolicy::Realtime(RealtimeThreadSchedulePolicy::Fifo),
            )
        });
        match result {
            Ok(()) => setup.fifo_priority = Some(config.realtime_priority),
            Err(e) => setup
                .warnings
                .push(fifo_refused(config.realtime_priority, &e)),
        }
    }
    setup
}

/// The warning when SCHED_FIFO at `priority` was refused with `error`: the reason in words and
/// what allows it.
fn fifo_refused(priority: u8, error: &thread_priority::Error) -> String {
    let reason = match error {
        thread_priority::Error::OS(code) => std::io::Error::from_raw_os_error(*code).to_string(),
        other => other.to_string(),
    };
    format!(
        "cannot use SCHED_FIFO priority {priority}: {reason}; running at normal priority, expect \
         more jitter. Allow it with LimitRTPRIO=90 in the unit, an `rtprio 90` line in \
         /etc/security/limits.d/ for a user running hgcd by hand, or CAP_SYS_NICE \
         (docs/install.md §5)"
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_refused_priority_is_explained_in_words_with_the_remedy() {
        let warning = fifo_refused(80, &thread_priority::Error::OS(libc::EPERM));
        assert!(!warning.contains("OS(1)"), "{warning}");
        assert!(
            warning.contains(&std::io::Error::from_raw_os_error(libc::EPERM).to_string()),
            "{warning}"
        );
        for remedy in ["LimitRTPRIO", "rtprio", "CAP_SYS_NICE", "docs/install.md"] {
            assert!(warning.contains(remedy), "{remedy}: {warning}");
        }
    }
}
