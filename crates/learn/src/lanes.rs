//! Independent jobs side by side: small problems do not split across threads (one 192-tet
//! assembly is a few microseconds of work per thread), so experiments run whole jobs
//! concurrently instead, one lane per thread.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

/// Free DOFs below which independent simulations (a dataset's trajectories, a loss
/// evaluation's rollouts, a policy's timed runs) run side by side, one per thread; larger
/// problems run one by one and use the threads inside each step (assembly, factorisation),
/// where they pay off.
pub(crate) const SIDE_BY_SIDE_MAX_DOFS: usize = 20_000;

/// Whether `jobs` jobs on problems of `free_dofs` free DOFs run side by side: with more
/// than one thread and one job, below [`SIDE_BY_SIDE_MAX_DOFS`].
pub(crate) fn worth_it(jobs: usize, free_dofs: usize) -> bool {
    rayon::current_num_threads().min(jobs) >= 2 && free_dofs <= SIDE_BY_SIDE_MAX_DOFS
}

/// A job: the lane's state, the job's index and a sink for its progress events.
pub(crate) type LaneJob<'a, S, T, E, P> =
    dyn Fn(&mut S, usize, &mut dyn FnMut(P)) -> Result<T, E> + Sync + 'a;

/// Runs jobs `0..jobs` on `lanes` (one thread each, with a one-thread rayon pool of its own
/// so that a job's timings are one core's and its parallel loops do not queue behind the
/// other lanes'), each lane taking the next job not yet taken. `run` gets the lane's state,
/// the job and a sink for progress events, which `progress` sees on this thread with the
/// job's index. Results come back in job order. After a failure no new job starts and every
/// earlier one has started, so the error returned is the first in job order, as when the
/// jobs run one by one. Which lane runs a job must not change its result: each job starts
/// from a state of its own.
pub(crate) fn side_by_side<S, T, E, P>(
    lanes: &mut [S],
    jobs: usize,
    run: &LaneJob<'_, S, T, E, P>,
    progress: &mut dyn FnMut(usize, P),
) -> Result<Vec<T>, E>
where
    S: Send,
    T: Send,
    E: Send,
    P: Send,
{
    enum Message<T, E, P> {
        Progress(usize, P),
        Done(usize, Result<T, E>),
    }
    let (next, failed) = (AtomicUsize::new(0), AtomicBool::new(false));
    let (sender, receiver) = std::sync::mpsc::channel();
    let mut done: Vec<Option<Result<T, E>>> = (0..jobs).map(|_| None).collect();
    std::thread::scope(|scope| {
        for lane in lanes.iter_mut() {
            let sender = sender.clone();
            let (next, failed) = (&next, &failed);
            scope.spawn(move || {
                let mut work = move || {
                    while !failed.load(Ordering::SeqCst) {
                        let k = next.fetch_add(1, Ordering::SeqCst);
                        if k >= jobs {
                            break;
                        }
                        let mut report = |p| drop(sender.send(Message::Progress(k, p)));
                        let out = run(lane, k, &mut report);
                        failed.fetch_or(out.is_err(), Ordering::SeqCst);
                        drop(sender.send(Message::Done(k, out)));
                    }
                };
                // Without a pool of its own (no thread to spare) the lane uses the global one.
                match rayon::ThreadPoolBuilder::new().num_threads(1).build() {
                    Ok(pool) => pool.install(work),
                    Err(_) => work(),
                }
            });
        }
        drop(sender);
        for message in receiver {
            match message {
                Message::Progress(k, p) => progress(k, p),
                Message::Done(k, out) => done[k] = Some(out),
            }
        }
    });
    // The jobs that ran, up to the first failure.
    done.into_iter().map_while(|d| d).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn results_come_back_in_job_order_with_the_first_error() {
        let mut lanes = vec![0usize; 3];
        let mut seen = Vec::new();
        let square = |count: &mut usize, k: usize, report: &mut dyn FnMut(usize)| {
            *count += 1;
            report(k);
            Ok::<_, String>(k * k)
        };
        let out = side_by_side(&mut lanes, 20, &square, &mut |k, p| seen.push((k, p)));
        assert_eq!(out, Ok((0..20).map(|k| k * k).collect()));
        assert_eq!(lanes.iter().sum::<usize>(), 20);
        seen.sort_unstable();
        assert_eq!(seen, (0..20).map(|k| (k, k)).collect::<Vec<_>>());
        let fail = |_: &mut usize, k: usize, _: &mut dyn FnMut(())| {
            if k == 5 || k == 7 { Err(k) } else { Ok(k) }
        };
        assert_eq!(side_by_side(&mut lanes, 20, &fail, &mut |_, _| {}), Err(5));
    }

    #[test]
    fn each_lane_runs_on_one_thread() {
        let mut lanes = vec![(); 2];
        let threads =
            |_: &mut (), _: usize, _: &mut dyn FnMut(())| Ok::<_, ()>(rayon::current_num_threads());
        let out = side_by_side(&mut lanes, 4, &threads, &mut |_, _| {}).unwrap();
        assert_eq!(out, vec![1; 4]);
    }
}
