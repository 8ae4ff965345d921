//! Vectors refilled step after step. A step's whole-grid arrays are built into the memory
//! of the last step's (see `world::step::Spare`); a vector refilled by `push` or `resize`
//! grows by doubling, so a count that creeps up by a few cells a step (the liquid's) would
//! leave every kept vector up to twice its size. [`clear_for`] keeps a vector's memory only
//! while it fits.

use rayon::prelude::*;

/// Empties `v` to hold `len` elements: its memory is kept when it holds `len` and not twice
/// as many, and replaced otherwise by room for `len` and a thirty-second more (so a slowly
/// growing count does not reallocate every time).
pub fn clear_for<T>(v: &mut Vec<T>, len: usize) {
    v.clear();
    if v.capacity() < len || v.capacity() > 2 * len + 64 {
        *v = Vec::with_capacity(len + len / 32);
    }
}

/// `v` set to `len` copies of `value`, its memory kept as [`clear_for`] keeps it; filled on
/// two threads when long (a system's stencil and faces are tens of MB a step).
pub fn refill<T: Clone + Send + Sync>(v: &mut Vec<T>, len: usize, value: T) {
    clear_for(v, len);
    if len >= crate::math::par::MIN_LEN {
        v.par_extend(rayon::iter::repeat_n(value, len));
    } else {
        v.resize(len, value);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn memory_is_kept_while_it_fits_and_never_doubles() {
        let mut v: Vec<u32> = Vec::new();
        refill(&mut v, 1000, 7);
        let (cap, ptr) = (v.capacity(), v.as_ptr());
        assert_eq!(cap, 1031);
        // A count creeping up within the slack keeps the memory.
        for len in [1001, 1010, 1031, 900] {
            refill(&mut v, len, 1);
            assert_eq!((v.capacity(), v.as_ptr()), (cap, ptr));
            assert_eq!(v.len(), len);
            assert!(v.iter().all(|&x| x == 1));
        }
        // Past it, room for the new count (not twice the old capacity).
        refill(&mut v, 1032, 0);
        assert_eq!(v.capacity(), 1032 + 32);
        // Far smaller: the memory goes.
        refill(&mut v, 10, 0);
        assert!(v.capacity() < 100);
    }

    #[test]
    fn long_refills_are_filled_in_place_too() {
        // Past the parallel threshold: the same memory kept, every element set.
        let n = 5 * crate::math::par::MIN_LEN + 17;
        let mut v: Vec<[u32; 6]> = Vec::new();
        refill(&mut v, n, [3; 6]);
        let (cap, ptr) = (v.capacity(), v.as_ptr());
        v[n / 2] = [0; 6];
        refill(&mut v, n - 100, [9; 6]);
        assert_eq!((v.capacity(), v.as_ptr()), (cap, ptr));
        assert_eq!(v.len(), n - 100);
        assert!(v.iter().all(|&x| x == [9; 6]));
    }
}
