//! How the process's allocator treats freed memory.
//!
//! candle allocates a fresh buffer for every tensor an operation produces and frees it
//! soon after. glibc's `malloc` serves blocks above a threshold (128 KiB, rising
//! dynamically) with `mmap` and returns them with `munmap`, and trims the heap's top
//! whenever more than 128 KiB is free, so a training step would keep mapping,
//! zero-filling and unmapping the same few hundred megabytes. [`keep_freed_memory`]
//! raises both thresholds once at start-up ([`MMAP_THRESHOLD`], [`TRIM_THRESHOLD`]), so
//! freed blocks are reused: less system time for somewhat more resident memory. With
//! other C libraries it does nothing. Tested: the settings apply on glibc and
//! allocation still works; the effect on training time is in `docs/performance.md`
//! ("The allocator").

/// Blocks up to this size come from the heap instead of their own mapping (glibc's
/// largest allowed value on 64-bit targets).
pub const MMAP_THRESHOLD: usize = 32 << 20;

/// Free memory at the top of the heap is returned to the system only beyond this.
pub const TRIM_THRESHOLD: usize = 1 << 30;

/// Makes glibc keep freed memory for reuse (see the module docs). Call once, early in
/// `main`, before threads start; returns whether the settings were applied.
pub fn keep_freed_memory() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: `mallopt` only changes allocator parameters, under the main arena's
        // lock; other threads read the thresholds unlocked, so `main` calls this before
        // starting any (the unit test calls it under the test harness, where a racing
        // allocation sees either the old or the new threshold).
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD as libc::c_int) == 1
                && libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD as libc::c_int) == 1
        }
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        false
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn settings_apply_on_glibc() {
        let applied = super::keep_freed_memory();
        assert_eq!(
            applied,
            cfg!(all(target_os = "linux", target_env = "gnu")),
            "mallopt refused a setting"
        );
        // Allocation still works, large and small.
        let big = vec![1u8; 64 << 20];
        let small: Vec<u32> = (0..1000).collect();
        assert_eq!(big[big.len() - 1] as usize + small[999] as usize, 1000);
    }
}
