//! Runs of consecutive rows whose neighbours are each the previous row's plus one (a row of
//! a deep pool), which the solvers read as contiguous slices instead of by index.

/// Visits the entries `first..end` in order, split by `runs` (sorted, disjoint
/// `(start, len)`): `part(None, a, b)` for each stretch `a..b` outside the runs, and
/// `part(Some(start), a, b)` for the part `a..b` of a run that lies inside (`start`: the
/// run's first entry, whose neighbour indices the part offsets by `a − start`).
#[inline(always)]
pub fn walk(
    runs: &[(u32, u32)],
    first: usize,
    end: usize,
    mut part: impl FnMut(Option<usize>, usize, usize),
) {
    let mut i = first;
    let mut next = runs.partition_point(|&(s, l)| (s + l) as usize <= first);
    while i < end {
        let (rs, re) = match runs.get(next) {
            Some(&(s, l)) if (s as usize) < end => (s as usize, (s + l) as usize),
            _ => (end, end),
        };
        if rs > i {
            part(None, i, rs);
        }
        if rs >= end {
            break;
        }
        let (a, b) = (rs.max(i), re.min(end));
        part(Some(rs), a, b);
        i = b;
        next += 1;
    }
}

/// The shortest run [`find`] keeps.
pub const SHORTEST: usize = 4;

/// The maximal runs of at least [`SHORTEST`] entries among `0..len` in which every entry
/// after the first `follows` the one before it.
pub fn find(len: usize, follows: impl Fn(usize) -> bool + Sync) -> Vec<(u32, u32)> {
    use rayon::prelude::*;
    let link: Vec<bool> = (0..len)
        .into_par_iter()
        .with_min_len(crate::math::par::MIN_LEN)
        .map(|i| i > 0 && follows(i))
        .collect();
    let mut runs = Vec::new();
    let mut start = 0;
    for i in 1..=len {
        if i == len || !link[i] {
            if i - start >= SHORTEST {
                runs.push((start as u32, (i - start) as u32));
            }
            start = i;
        }
    }
    runs
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_entry_is_visited_once_in_order() {
        let runs = find(40, |i| !matches!(i, 4 | 5 | 6 | 7 | 20 | 31 | 34));
        // 4, 5 and 6 stand alone and 31..34 is three long: too short to keep.
        assert_eq!(runs, vec![(0, 4), (7, 13), (20, 11), (34, 6)]);
        for (first, end) in [(0, 40), (3, 25), (8, 9), (21, 21), (30, 40)] {
            let mut seen = Vec::new();
            walk(&runs, first, end, |start, a, b| {
                if let Some(s) = start {
                    assert!(runs.iter().any(|&(rs, l)| rs as usize == s && b <= s + l as usize));
                }
                seen.extend((a..b).map(|i| (i, start.is_some())));
            });
            let want: Vec<(usize, bool)> = (first..end)
                .map(|i| (i, runs.iter().any(|&(s, l)| (s..s + l).contains(&(i as u32)))))
                .collect();
            assert_eq!(seen, want, "{first}..{end}");
        }
    }
}
