//! Two pieces of independent work side by side: how the learner's step uses the core the
//! actors leave idle.
//!
//! A SAC step is a chain of small products (256-wide layers on a minibatch of 256), too small
//! for the matrix kernel to split well, but half of its work comes in pairs that do not
//! depend on each other: the two critics, the policy on two minibatches, the target update
//! beside the actor's backward pass. [`Par::join`] runs one piece of a pair on the calling
//! thread and the other on one helper thread that sleeps between jobs (it never spins against
//! the actors). Each piece runs the same operations on the same inputs as one after the other
//! would, so the results are bit for bit the same with one thread or two.

use std::panic::{catch_unwind, resume_unwind, AssertUnwindSafe};
use std::sync::mpsc;
use std::thread::JoinHandle;

type Job = Box<dyn FnOnce() + Send>;

/// Where the second piece of a pair runs: after the first on the calling thread, or beside it
/// on a helper thread.
#[derive(Debug, Default)]
pub struct Par {
    helper: Option<Helper>,
}

#[derive(Debug)]
struct Helper {
    jobs: Option<mpsc::Sender<Job>>,
    thread: Option<JoinHandle<()>>,
}

impl Par {
    /// Pairs on `threads` threads: 1 runs them one after the other, 2 (or more: a pair has two
    /// pieces) side by side.
    pub fn new(threads: usize) -> std::io::Result<Self> {
        if threads < 2 {
            return Ok(Self::default());
        }
        let (jobs, rx) = mpsc::channel::<Job>();
        let thread = std::thread::Builder::new()
            .name("pbrl-learner-2".into())
            .spawn(move || {
                while let Ok(job) = rx.recv() {
                    job();
                }
            })?;
        Ok(Self {
            helper: Some(Helper {
                jobs: Some(jobs),
                thread: Some(thread),
            }),
        })
    }

    /// How many threads a pair runs on (1 or 2).
    pub fn threads(&self) -> usize {
        if self.helper.is_some() {
            2
        } else {
            1
        }
    }

    /// `(a(), b())`: `a` on this thread, `b` beside it on the helper (or after `a` without
    /// one). A panic in `b` is raised here.
    pub fn join<A, B>(
        &self,
        a: impl FnOnce() -> A,
        b: impl FnOnce() -> B + Send + 'static,
    ) -> (A, B)
    where
        B: Send + 'static,
    {
        let Some(jobs) = self.helper.as_ref().and_then(|h| h.jobs.as_ref()) else {
            let ra = a();
            return (ra, b());
        };
        let (tx, rx) = mpsc::sync_channel(1);
        let job: Job = Box::new(move || {
            let _ = tx.send(catch_unwind(AssertUnwindSafe(b)));
        });
        if let Err(mpsc::SendError(job)) = jobs.send(job) {
            // NOTE: cannot happen while `self` holds the sender (the helper catches every
            // panic of a job and goes on); run the piece here all the same.
            job();
        }
        let ra = a();
        match rx.recv() {
            Ok(Ok(rb)) => (ra, rb),
            Ok(Err(panic)) => resume_unwind(panic),
            Err(_) => panic!("the learner's helper thread ended without an answer"),
        }
    }
}

impl Drop for Helper {
    fn drop(&mut self) {
        drop(self.jobs.take());
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The widest SIMD path the matrix kernel (gemm, built with `x86-v4`) takes on this CPU,
/// detected as gemm detects it.
pub fn simd_path() -> &'static str {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::is_x86_feature_detected as has;
        let v3 = has!("avx2") && has!("fma") && has!("bmi2") && has!("lzcnt");
        if v3
            && has!("avx512f")
            && has!("avx512bw")
            && has!("avx512cd")
            && has!("avx512dq")
            && has!("avx512vl")
        {
            "AVX-512 (x86-64-v4)"
        } else if v3 {
            "AVX2 + FMA (x86-64-v3)"
        } else {
            "SSE2 (portable x86-64)"
        }
    }
    #[cfg(target_arch = "aarch64")]
    {
        "NEON (aarch64)"
    }
    #[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
    {
        "scalar"
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_pieces_run_and_their_results_come_back_in_order() {
        for threads in [1, 2] {
            let par = Par::new(threads).unwrap();
            assert_eq!(par.threads(), threads);
            let here = std::thread::current().id();
            let (a, (b, where_b)) =
                par.join(|| 3 * 7, move || (6 * 7, std::thread::current().id()));
            assert_eq!((a, b), (21, 42));
            assert_eq!(where_b == here, threads == 1, "{threads} thread(s)");
        }
    }

    #[test]
    fn a_panic_on_the_helper_is_raised_by_join() {
        let par = Par::new(2).unwrap();
        let r = catch_unwind(AssertUnwindSafe(|| par.join(|| 1, || panic!("boom"))));
        let msg = r.unwrap_err();
        assert_eq!(msg.downcast_ref::<&str>(), Some(&"boom"));
        // The helper carries on with the next pair.
        assert_eq!(par.join(|| 1, || 2), (1, 2));
    }
}
