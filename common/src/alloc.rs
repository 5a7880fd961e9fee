//! The process's allocator, set once at start.

/// Keep the process's resident memory at what it holds (glibc; elsewhere nothing): call it
/// first in `main`, before any thread starts. Two settings of glibc's allocator, both from
/// the soak (`deploy/soak.sh`, results/deploy/README.md):
/// - A fixed mmap threshold. A checkpoint encodes its state (about 18 MB on the feeding
///   world with the soak's buffers) and each replay segment (13-40 MB) into one buffer each.
///   glibc serves a block that large from mmap and returns it when freed, but the first
///   free raises the threshold to that block's size, so later checkpoints' buffers come from
///   the heap and leave it at a new high-water mark. Fixed at 4 MiB, those buffers stay in
///   mmap; the labels, trajectories and minibatches, all far smaller, stay in the heap.
/// - At most two arenas. glibc gives threads that allocate at once arenas of their own (up
///   to 8 a core), each a heap that grows on its own and hardly shrinks; the learner's
///   updates, its feedback jobs (a thread each), zenoh's and tokio's threads all allocate.
///
/// glibc's own variables, `MALLOC_MMAP_THRESHOLD_` and `MALLOC_ARENA_MAX`, where set, rule.
pub fn steady_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        const MMAP_THRESHOLD: libc::c_int = 4 << 20;
        const ARENAS: libc::c_int = 2;
        // SAFETY: mallopt only sets parameters of glibc's allocator; they change where later
        // blocks come from, never a block already handed out.
        unsafe {
            if std::env::var_os("MALLOC_MMAP_THRESHOLD_").is_none() {
                libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD);
            }
            if std::env::var_os("MALLOC_ARENA_MAX").is_none() {
                libc::mallopt(libc::M_ARENA_MAX, ARENAS);
            }
        }
    }
}
