//! The VJP of an explicit step taken range by range in parallel: the step's
//! output split into fixed ranges of rows (2D) or slabs (3D), each range's
//! adjoint (Enzyme's, of a function that computes that range alone) run on
//! its own thread, the partial input adjoints summed in the order of the
//! ranges. The ranges depend on the grid alone, so the result is the same
//! for any thread count.

use std::ops::Range;

use diffsim_solvers::par::{SUM_PIECE, for_pieces};
use rayon::prelude::*;

use crate::op::Vjp;

thread_local! {
    /// The buffers of the ranges past the first, kept between calls.
    static PARTS: std::cell::Cell<Vec<Vec<f64>>> = const { std::cell::Cell::new(Vec::new()) };
}

/// The fixed ranges `n` rows or slabs are split into: two from 16 on, else
/// one. Each range past the first costs one state of memory; two keep the
/// two cores of the machines here busy.
pub fn split_ranges(n: usize) -> Vec<Range<usize>> {
    let count = (n / 8).clamp(1, 2);
    (0..count).map(|r| r * n / count..(r + 1) * n / count).collect()
}

/// `dx += Jᵀ·dy` of a step whose output is the union of `ranges`: `op(r)`
/// is the step restricted to range `r` (its output the fields' pieces
/// `pieces(r)`, `(start, len)` in the full output, packed in that order).
/// `dy` is zeroed after (the VJP contract).
pub fn vjp_over_ranges<R: Vjp>(
    ranges: &[Range<usize>],
    op: impl Fn(Range<usize>) -> R + Sync,
    pieces: impl Fn(&Range<usize>) -> Vec<(usize, usize)> + Sync,
    x: &[f64],
    dy: &mut [f64],
    dx: &mut [f64],
) {
    let n = dx.len();
    let mut parts = PARTS.take();
    parts.resize_with(ranges.len(), Vec::new);
    let (first, rest) = parts.split_at_mut(1);
    // The first range's adjoint straight into dx (its buffer holds only
    // dy_0), each other range's into its own buffer `[dx_r | dy_r]`, all at
    // once; dy_r gathered from dy.
    let dy_read: &[f64] = dy;
    let range_vjp = |r: &Range<usize>, buf: &mut Vec<f64>, own: usize, dx: Option<&mut [f64]>| {
        let ps = pieces(r);
        buf.clear();
        buf.resize(own + ps.iter().map(|p| p.1).sum::<usize>(), 0.0);
        let (dx_r, dy_r) = buf.split_at_mut(own);
        let mut o = 0;
        for (start, len) in ps {
            dy_r[o..o + len].copy_from_slice(&dy_read[start..start + len]);
            o += len;
        }
        op(r.clone()).vjp(x, &[], dy_r, dx.unwrap_or(dx_r), &mut []);
    };
    rayon::join(
        || range_vjp(&ranges[0], &mut first[0], 0, Some(&mut *dx)),
        || rest.par_iter_mut().zip(&ranges[1..]).for_each(|(buf, r)| range_vjp(r, buf, n, None)),
    );
    // dx += Σ_r dx_r, in the order of the ranges.
    let rest = &parts[1..];
    for_pieces(dx, SUM_PIECE, |k, d| {
        let o = k * SUM_PIECE;
        for part in rest {
            for (d, &v) in d.iter_mut().zip(&part[o..o + SUM_PIECE.min(n - o)]) {
                *d += v;
            }
        }
    });
    PARTS.set(parts);
    dy.fill(0.0);
}
