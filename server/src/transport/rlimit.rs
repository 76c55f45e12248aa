//! The open-file limit, and the connection cap it leaves room for.

use std::io;

/// Raises this process's soft limit on open files to its hard limit, logging both, and returns
/// the soft limit now in force (`None` where there is no such limit to read).
pub fn raise_descriptor_limit() -> Option<u64> {
    #[cfg(unix)]
    {
        let mut limit = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: getrlimit writes into the struct it is given.
        if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } != 0 {
            tracing::warn!(error = %io::Error::last_os_error(), "reading RLIMIT_NOFILE");
            return None;
        }
        let before = limit.rlim_cur;
        if limit.rlim_cur < limit.rlim_max {
            let raised = libc::rlimit {
                rlim_cur: limit.rlim_max,
                rlim_max: limit.rlim_max,
            };
            // SAFETY: setrlimit reads the struct it is given.
            if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &raised) } == 0 {
                limit.rlim_cur = limit.rlim_max;
            } else {
                tracing::warn!(error = %io::Error::last_os_error(), "raising RLIMIT_NOFILE");
            }
        }
        tracing::info!(
            soft_before = before,
            soft = limit.rlim_cur,
            hard = limit.rlim_max,
            "open file limit"
        );
        Some(limit.rlim_cur)
    }
    #[cfg(not(unix))]
    None
}

/// The connection cap to use under a descriptor limit of `nofile`: `wanted`, or less when that
/// would leave fewer than a quarter of the descriptors (at least 64) for everything else (the
/// data directory's files, the listener, outgoing pushes).
pub fn cap_for(wanted: usize, nofile: Option<u64>) -> usize {
    match nofile {
        Some(n) => {
            let spare = (n / 4).max(64);
            wanted.min(n.saturating_sub(spare).max(1) as usize)
        }
        None => wanted,
    }
    .max(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cap_leaves_room_for_other_descriptors() {
        assert_eq!(cap_for(4096, Some(20_000)), 4096);
        assert_eq!(cap_for(4096, Some(1024)), 768);
        assert_eq!(cap_for(4096, Some(100)), 36);
        assert_eq!(cap_for(10, None), 10);
    }
}
