//! Deterministic parallel loops the grid's stages share.

use rayon::prelude::*;

/// Elements of an index list handed to rayon as one piece.
const CHUNK: usize = 4096;

/// The fewest elements a parallel loop splits off: below it a loop runs on the calling
/// thread, since waking a worker costs more than a small grid's loop (the block drop's
/// 10,000 cells take a hundred-odd such loops a step).
pub const MIN_LEN: usize = 16_384;

/// A copy of `v`, made in pieces of at least [`MIN_LEN`] elements in parallel (a whole-grid
/// array or the marker particles: a copy on one thread leaves the other idle).
pub fn copied<T: Copy + Send + Sync>(v: &[T]) -> Vec<T> {
    v.par_iter().with_min_len(MIN_LEN).copied().collect()
}

/// For a loop over pieces of `piece` elements each: the fewest pieces to split off (see
/// [`MIN_LEN`]).
pub fn min_pieces(piece: usize) -> usize {
    (MIN_LEN / piece.max(1)).max(1)
}

/// Calls `f(n, e, &mut out[key(e)])` for every entry `e` of `list` (`n` its position), in
/// parallel. The keys must
/// increase strictly along `list` (a sorted list of faces or cells), so each call owns its
/// element: `out` is split at the chunks' first keys into disjoint pieces. Each element is
/// written by one call, whatever the thread count.
pub fn for_each_keyed_mut<E, T, K, F>(out: &mut [T], list: &[E], key: K, f: F)
where
    E: Sync,
    T: Send,
    K: Fn(&E) -> usize + Sync,
    F: Fn(usize, &E, &mut T) + Sync,
{
    debug_assert!(list.windows(2).all(|w| key(&w[0]) < key(&w[1])), "keys not increasing");
    let mut parts = Vec::with_capacity(list.len() / CHUNK + 1);
    let (mut rest, mut offset) = (out, 0usize);
    let chunks: Vec<&[E]> = list.chunks(CHUNK).collect();
    for (n, chunk) in chunks.iter().enumerate() {
        let lo = key(&chunk[0]);
        let hi = chunks.get(n + 1).map_or(offset + rest.len(), |next| key(&next[0]));
        let (_, tail) = std::mem::take(&mut rest).split_at_mut(lo - offset);
        let (mine, tail) = tail.split_at_mut(hi - lo);
        parts.push((n * CHUNK, *chunk, mine, lo));
        (rest, offset) = (tail, hi);
    }
    parts.into_par_iter().with_min_len(min_pieces(CHUNK)).for_each(|(first, chunk, mine, lo)| {
        for (n, e) in chunk.iter().enumerate() {
            f(first + n, e, &mut mine[key(e) - lo]);
        }
    });
}

/// Σ f(e) over `list` in fixed chunks whose partial sums are added in order: the same bits
/// for any thread count.
pub fn sum_by<E, F>(list: &[E], f: F) -> f64
where
    E: Sync,
    F: Fn(&E) -> f64 + Sync,
{
    let parts: Vec<f64> = list
        .par_chunks(CHUNK)
        .with_min_len(min_pieces(CHUNK))
        .map(|c| c.iter().map(&f).sum::<f64>())
        .collect();
    parts.iter().sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_keyed_element_is_written_once_by_its_entry() {
        let list: Vec<u32> = (0..20_000u32).map(|i| 3 * i + (i % 3)).collect();
        let mut out = vec![0u64; 60_010];
        for_each_keyed_mut(
            &mut out,
            &list,
            |&i| i as usize,
            |n, &i, x| *x += (n + i as usize) as u64,
        );
        for (k, x) in out.iter().enumerate() {
            let at = list.binary_search(&(k as u32));
            assert_eq!(*x, at.map_or(0, |n| (n + k) as u64), "element {k}");
        }
    }

    #[test]
    fn sums_do_not_depend_on_the_thread_count() {
        let list: Vec<f64> = (0..50_000).map(|i| ((i * 7919) % 1009) as f64 / 7.0).collect();
        let run = |t: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(t).build().unwrap();
            pool.install(|| sum_by(&list, |x| x * x))
        };
        assert_eq!(run(1).to_bits(), run(2).to_bits());
    }
}
