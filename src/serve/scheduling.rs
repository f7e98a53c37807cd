//! How the server's threads are scheduled against each other on a busy core.

/// Marks the calling thread SCHED_BATCH (Linux): it keeps its fair share of the CPU, but when
/// woken it waits for the running thread's slice instead of preempting it. The request-handling
/// threads take this, so that a batch worker answering a batch is not interrupted by the handler
/// its first answer woke, once per answer: it finishes the batch and the handlers then write
/// every answer in one go. Elsewhere, and where the kernel refuses, nothing changes.
pub fn handlers_do_not_preempt() {
    #[cfg(target_os = "linux")]
    {
        let param = libc::sched_param { sched_priority: 0 };
        // SAFETY: pid 0 is the calling thread; `param` is a valid sched_param for the call.
        let refused = unsafe { libc::sched_setscheduler(0, libc::SCHED_BATCH, &param) } != 0;
        if refused {
            tracing::debug!(
                error = %std::io::Error::last_os_error(),
                "could not make a request-handling thread SCHED_BATCH"
            );
        }
    }
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    #[test]
    fn a_handler_thread_becomes_sched_batch_and_others_do_not() {
        let policy = |mark: bool| {
            std::thread::spawn(move || {
                if mark {
                    super::handlers_do_not_preempt();
                }
                // SAFETY: pid 0 is the calling thread.
                unsafe { libc::sched_getscheduler(0) }
            })
            .join()
            .expect("the thread ran")
        };
        assert_eq!(policy(true), libc::SCHED_BATCH);
        assert_eq!(policy(false), libc::SCHED_OTHER);
    }
}
