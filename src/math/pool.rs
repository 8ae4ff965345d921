//! Running a step's work on rayon's pool: from inside it, so its many short parallel loops
//! are not each handed over from outside, and with the other workers spinning through a
//! step when that pays.

use std::cell::OnceCell;
use std::sync::atomic::{AtomicBool, Ordering};

/// How a step's work is spread over the threads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Spread {
    /// On one thread of a pool of its own: a grid too small for its parallel loops to pay
    /// for handing work to another thread.
    Serial,
    /// On rayon's pool, the other workers sleeping between the step's loops.
    Parallel,
    /// On rayon's pool, the other workers spinning through the step
    /// ([`on_pool_spinning`]).
    Spinning,
}

/// Grids of fewer cells than this run a step (and a backward step) on one thread: there
/// the second thread cost more than it saved, measured in docs/performance.md ("Defaults
/// chosen from the scene").
pub const SERIAL_BELOW: usize = 32_768;

/// Runs `f` spread as asked. The results are the same bits either way: every parallel
/// loop of a step is deterministic for any thread count.
pub fn run_spread<R: Send>(spread: Spread, f: impl FnOnce() -> R + Send) -> R {
    match spread {
        Spread::Serial if rayon::current_num_threads() > 1 => {
            with_own(&SERIAL, serial_pool, |pool| match pool {
                Some(pool) => pool.install(f),
                None => on_pool(f),
            })
        }
        Spread::Serial | Spread::Parallel => on_pool(f),
        Spread::Spinning => on_pool_spinning(true, f),
    }
}

thread_local! {
    /// This thread's one-thread pool of [`Spread::Serial`], made on first use (None if the
    /// thread could not be started: then the work runs on rayon's pool). A pool per calling
    /// thread, not one for the process: small simulations stepped side by side (a parallel
    /// loop over runs, a smoothed gradient's draws, central differences) each get a thread,
    /// where one shared pool queued them all on a single thread.
    static SERIAL: OnceCell<Option<rayon::ThreadPool>> = const { OnceCell::new() };
    /// This thread's one-thread pool of [`ahead`].
    static AHEAD: OnceCell<Option<rayon::ThreadPool>> = const { OnceCell::new() };
    /// This thread's one-thread pool of [`beside`].
    static BESIDE: OnceCell<Option<rayon::ThreadPool>> = const { OnceCell::new() };
    /// Whether this thread is that of a serial pool.
    static ON_SERIAL: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// `f` with this thread's pool in `cell`, made by `make` on first use.
fn with_own<R>(
    cell: &'static std::thread::LocalKey<OnceCell<Option<rayon::ThreadPool>>>,
    make: fn() -> Option<rayon::ThreadPool>,
    f: impl FnOnce(Option<&rayon::ThreadPool>) -> R,
) -> R {
    cell.with(|c| f(c.get_or_init(make).as_ref()))
}

/// A pool of one thread for [`Spread::Serial`], whose thread knows it is one.
fn serial_pool() -> Option<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .thread_name(|_| "diffluid-serial".into())
        .start_handler(|_| ON_SERIAL.with(|s| s.set(true)))
        .build()
        .ok()
}

/// `f` of every item, in order, run side by side on as many plain threads as rayon's pool
/// has (each taking the next item when it is done with one): for independent runs of
/// small simulations, each of which steps on its thread's own serial pool
/// ([`Spread::Serial`]). Not a rayon loop: a rayon worker that waits for a serial pool
/// takes other items meanwhile and starts them on its own pool, so that one worker can end
/// up holding every item while the others idle (a gradient check's 52 runs took as long as
/// on one thread that way).
pub fn side_by_side<T: Sync, R: Send>(items: &[T], f: impl Fn(&T) -> R + Sync) -> Vec<R> {
    use std::sync::atomic::AtomicUsize;
    use std::sync::Mutex;
    let threads = rayon::current_num_threads().clamp(1, items.len().max(1));
    if threads == 1 {
        return items.iter().map(f).collect();
    }
    let next = AtomicUsize::new(0);
    let out: Mutex<Vec<Option<R>>> = Mutex::new((0..items.len()).map(|_| None).collect());
    std::thread::scope(|s| {
        for _ in 0..threads {
            s.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(item) = items.get(i) else { break };
                let r = f(item);
                out.lock().unwrap_or_else(|e| e.into_inner())[i] = Some(r);
            });
        }
    });
    out.into_inner()
        .unwrap_or_else(|e| e.into_inner())
        .into_iter()
        .map(|r| r.expect("every item was run"))
        .collect()
}

/// `f` of every item in order, for independent runs of a simulation whose steps are spread
/// `spread`: side by side ([`side_by_side`]) where it steps on one thread
/// ([`Spread::Serial`]); else one after another here, as a larger grid's steps keep the
/// threads busy alone and its runs side by side would each hold a state.
pub fn runs<T: Sync, R: Send>(spread: Spread, items: &[T], f: impl Fn(&T) -> R + Sync) -> Vec<R> {
    if spread == Spread::Serial {
        side_by_side(items, f)
    } else {
        items.iter().map(f).collect()
    }
}

/// A pool of one thread named `name` (None if it could not be started).
fn one_thread(name: &'static str) -> Option<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new().num_threads(1).thread_name(move |_| name.into()).build().ok()
}

/// Runs `now` on this thread and `later` (work that a later call will read and that does
/// not depend on `now`) on a thread of its own at the same time, when this is the thread of
/// a serial step ([`Spread::Serial`]: the other threads idle); else `now`, then `later`.
/// `later` runs on a one-thread pool, so its parallel loops stay on its thread, as a serial
/// step's do. Nothing changes but where `later` runs: the results are the same bits.
pub fn ahead<A: Send, B: Send>(
    now: impl FnOnce() -> A + Send,
    later: impl FnOnce() -> B + Send,
) -> (A, B) {
    if !ON_SERIAL.with(|s| s.get()) {
        return on_two(None, now, later);
    }
    with_own(&AHEAD, || one_thread("diffluid-ahead"), |pool| on_two(pool, now, later))
}

/// [`ahead`] on the thread of a serial step; on rayon's pool, `rayon::join(now, later)`, so
/// that `later`'s loops fill what `now` leaves of the other threads (the gaps between its own
/// short loops). Nothing changes but where and when `later` runs: the same bits.
pub fn alongside<A: Send, B: Send>(
    now: impl FnOnce() -> A + Send,
    later: impl FnOnce() -> B + Send,
) -> (A, B) {
    if ON_SERIAL.with(|s| s.get()) || rayon::current_thread_index().is_none() {
        ahead(now, later)
    } else {
        rayon::join(now, later)
    }
}

/// Runs `now` here and `other` beside it, on a one-thread pool of its own, when both are
/// work of simulations whose steps are spread `spread` and that is [`Spread::Serial`] (so
/// they step on one thread either way) and a second thread is free: called from the thread
/// of a serial step or from outside rayon's pools with more than one thread. Else `now`,
/// then `other`. The results are the same bits either way. Not the pool of [`ahead`]: the
/// steps of `now` hand it work, which would wait behind `other`.
pub fn beside<A: Send, B: Send>(
    spread: Spread,
    now: impl FnOnce() -> A + Send,
    other: impl FnOnce() -> B + Send,
) -> (A, B) {
    let free = ON_SERIAL.with(|s| s.get())
        || (rayon::current_thread_index().is_none() && rayon::current_num_threads() > 1);
    if spread != Spread::Serial || !free {
        return on_two(None, now, other);
    }
    with_own(&BESIDE, || one_thread("diffluid-beside"), |pool| on_two(pool, now, other))
}

/// `now` here and `later` on `pool` at once, or one after the other without a pool.
fn on_two<A: Send, B: Send>(
    pool: Option<&rayon::ThreadPool>,
    now: impl FnOnce() -> A + Send,
    later: impl FnOnce() -> B + Send,
) -> (A, B) {
    let Some(pool) = pool else {
        let a = now();
        return (a, later());
    };
    let mut b = None;
    let a = pool.in_place_scope(|s| {
        s.spawn(|_| b = Some(later()));
        now()
    });
    (a, b.expect("the scope waited for `later`"))
}

/// Runs `f` on a thread of rayon's pool. A step makes dozens of short parallel loops; called
/// from a thread outside the pool, each one would hand its work over and put the caller to
/// sleep until it is done: a pair of context switches a loop, more than a small grid's loop
/// takes (measured in docs/performance.md, "Why the hot paths are written as they are").
/// Inside the pool, the caller takes part in its own loops. Cheap when already on the pool.
pub fn on_pool<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    rayon::scope(|_| f())
}

/// [`on_pool`], with the pool's other workers kept busy while `f` runs when `spin` (and the
/// pool has more than one thread): a job on each other worker takes pending work as soon as
/// `f`'s loops split it off ([`rayon::yield_now`]) and spins when there is none, so no loop
/// waits for a sleeping worker to wake. The job that lands on `f`'s own thread returns at
/// once, so `f` never waits on a spinner. Nothing changes but when the work is taken:
/// every loop's result is the same bits.
pub fn on_pool_spinning<R: Send>(spin: bool, f: impl FnOnce() -> R + Send) -> R {
    if !spin {
        return on_pool(f);
    }
    with_workers_awake(std::hint::spin_loop, f)
}

/// [`on_pool`], with the pool's other workers kept awake while `f` runs, as
/// [`on_pool_spinning`] keeps them, except that a worker with no work hands its core back to
/// the operating system (`std::thread::yield_now`) instead of spinning on it: on a machine
/// with nothing else to run it is taken back at once, on a busy one the other processes
/// lose little. For a linear solve, dozens of short loops a millisecond: between two of
/// them rayon would put the other worker to sleep, and the next would wait for it to wake.
/// The same bits.
pub fn on_pool_awake<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    with_workers_awake(std::thread::yield_now, f)
}

/// `f` on rayon's pool, each other worker taking pending work until `f` returns and calling
/// `idle` when there is none (see [`on_pool_spinning`]).
fn with_workers_awake<R: Send>(idle: fn(), f: impl FnOnce() -> R + Send) -> R {
    if rayon::current_num_threads() < 2 {
        return on_pool(f);
    }
    let done = AtomicBool::new(false);
    rayon::scope(|s| {
        let caller = rayon::current_thread_index();
        let done = &done;
        for _ in 1..rayon::current_num_threads() {
            s.spawn(move |_| {
                if rayon::current_thread_index() == caller {
                    return;
                }
                while !done.load(Ordering::Acquire) {
                    if rayon::yield_now() != Some(rayon::Yield::Executed) {
                        idle();
                    }
                }
            });
        }
        // Set when `f` returns or unwinds: a panic in `f` must not leave the spinners (and
        // the scope, which waits for them) running.
        struct Done<'a>(&'a AtomicBool);
        impl Drop for Done<'_> {
            fn drop(&mut self) {
                self.0.store(true, Ordering::Release);
            }
        }
        let _done = Done(done);
        f()
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;

    /// `ahead` and `beside` return both results; on the serial pool (and from outside the
    /// pools, for `beside`) the second job runs on another thread, elsewhere on this one.
    #[test]
    fn two_jobs_return_both_results_and_run_apart_when_serial() {
        let id = || std::thread::current().id();
        assert_eq!(ahead(|| 1, || 2), (1, 2));
        assert_eq!(alongside(|| 1, || 2), (1, 2));
        assert_eq!(on_pool(|| alongside(|| 1, || 2)), (1, 2));
        let (a, b) = ahead(id, id);
        assert_eq!(a, b, "outside the serial pool, one after the other");
        let (a, b) = run_spread(Spread::Serial, || ahead(id, id));
        let (c, d) = beside(Spread::Serial, id, id);
        let (e, f) = beside(Spread::Parallel, id, id);
        assert_eq!(e, f, "a parallel simulation's work is not split off");
        if rayon::current_num_threads() > 1 {
            assert_ne!(a, b);
            assert_ne!(c, d);
        }
    }

    /// `side_by_side` gives every item's result in the items' order, runs each item once,
    /// and spreads them over more than one thread when rayon has more; each calling thread
    /// steps its serial work on a pool of its own, so two of them do not share one.
    #[test]
    fn side_by_side_keeps_order_and_each_thread_has_its_own_serial_pool() {
        use std::sync::atomic::AtomicUsize;
        use std::sync::Mutex;
        let items: Vec<usize> = (0..57).collect();
        let calls = AtomicUsize::new(0);
        let threads = Mutex::new(std::collections::HashSet::new());
        let serial = Mutex::new(std::collections::HashSet::new());
        let out = side_by_side(&items, |&i| {
            calls.fetch_add(1, Ordering::Relaxed);
            threads.lock().unwrap().insert(std::thread::current().id());
            let on = run_spread(Spread::Serial, || std::thread::current().id());
            serial.lock().unwrap().insert(on);
            // Long enough that the first thread cannot take every item before the others start.
            std::thread::sleep(std::time::Duration::from_millis(2));
            i * i
        });
        assert_eq!(out, items.iter().map(|i| i * i).collect::<Vec<_>>());
        assert_eq!(calls.load(Ordering::Relaxed), items.len());
        assert!(side_by_side(&[] as &[usize], |&i| i).is_empty());
        if rayon::current_num_threads() > 1 {
            let (t, s) = (threads.lock().unwrap().len(), serial.lock().unwrap().len());
            assert!(t > 1, "one thread ran every item");
            assert_eq!(s, t, "{t} threads stepped their serial work on {s} pools");
        }
    }

    /// With spinning (or awake) workers, a parallel sum on a pool of two threads is the same
    /// bits as without, nested calls return, and a panic in the work reaches the caller instead of
    /// leaving the spinners running (the call would never return).
    #[test]
    fn spinning_workers_change_nothing_and_stop_on_a_panic() {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
        let x: Vec<f64> = (0..1_000_000).map(|i| (i as f64 * 0.37).sin()).collect();
        let sum = |x: &[f64]| x.par_chunks(4096).map(|c| c.iter().sum::<f64>()).collect::<Vec<_>>();
        pool.install(|| {
            let plain = on_pool(|| sum(&x));
            for spin in [false, true] {
                let nested = on_pool_spinning(spin, || on_pool_spinning(spin, || sum(&x)));
                assert_eq!(nested, plain);
            }
            let awake = on_pool_spinning(true, || on_pool_awake(|| on_pool_awake(|| sum(&x))));
            assert_eq!(awake, plain);
        });
        // On a thread of its own, so that spinners left running fail the test, not hang it.
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let caught = pool.install(|| {
                std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    on_pool_spinning(true, || {
                        let _ = sum(&x);
                        panic!("in the work")
                    })
                }))
            });
            tx.send(caught.is_err()).unwrap();
        });
        let panicked = rx.recv_timeout(std::time::Duration::from_secs(60));
        assert_eq!(panicked, Ok(true), "the panic reached the caller and the spinners stopped");
    }
}
