//! Tile binning: every splat goes to each 16×16 tile its extent box touches; within a tile the splats
//! are ordered by camera depth, ties by index, so the order (and every result) is deterministic.

use rayon::prelude::*;

use super::project::Projected;

/// Per-tile depth-sorted splat lists in one flat array (CSR layout).
#[derive(Debug, Default)]
pub(crate) struct Bins {
    /// `ids[offsets[t]..offsets[t + 1]]` are the splats of tile `t`, front to back.
    pub offsets: Vec<usize>,
    pub ids: Vec<u32>,
}

impl Bins {
    pub fn tile(&self, t: usize) -> &[u32] {
        &self.ids[self.offsets[t]..self.offsets[t + 1]]
    }

    pub fn num_pairs(&self) -> usize {
        self.ids.len()
    }
}

/// Bin projected splats (an empty rectangle = culled) into `tiles_x × tiles_y` tiles.
pub(crate) fn bin(proj: &[Projected], tiles_x: usize, tiles_y: usize) -> Bins {
    let num_tiles = tiles_x * tiles_y;
    let mut offsets = vec![0usize; num_tiles + 1];
    for p in proj {
        let r = &p.rect;
        for ty in r.y0 as usize..r.y1 as usize {
            for tx in r.x0 as usize..r.x1 as usize {
                offsets[ty * tiles_x + tx + 1] += 1;
            }
        }
    }
    for t in 0..num_tiles {
        offsets[t + 1] += offsets[t];
    }
    // Sort key: depth bits (positive floats order like their bits) above the index. Keys enter each
    // tile in index order, so a stable sort by depth breaks ties by index.
    let mut keys = vec![0u64; offsets[num_tiles]];
    let mut cursor = offsets[..num_tiles].to_vec();
    for (i, p) in proj.iter().enumerate() {
        let (r, key) = (&p.rect, (u64::from(p.splat.z.to_bits()) << 32) | i as u64);
        for ty in r.y0 as usize..r.y1 as usize {
            for tx in r.x0 as usize..r.x1 as usize {
                let c = &mut cursor[ty * tiles_x + tx];
                keys[*c] = key;
                *c += 1;
            }
        }
    }
    let mut scratch = vec![0u64; keys.len()];
    split_by_offsets(&mut keys, &offsets)
        .into_par_iter()
        .zip(split_by_offsets(&mut scratch, &offsets))
        .for_each(|(tile, tmp)| sort_by_depth(tile, tmp));
    let ids = keys.par_iter().map(|k| *k as u32).collect();
    Bins { offsets, ids }
}

/// Lists up to this long are sorted by comparison (a radix pass costs a 256-entry histogram).
const SMALL_LIST: usize = 64;

/// Sort one tile's keys by depth (their upper 32 bits), stably: an LSD radix sort, 8 bits a pass,
/// through `tmp` (same length); a pass whose digit is the same for every key is skipped (the depths of
/// one view share their top bits). Several times faster than a comparison sort of long lists.
fn sort_by_depth(keys: &mut [u64], tmp: &mut [u64]) {
    if keys.len() <= SMALL_LIST {
        // The index in the low bits makes the full-key order the stable depth order.
        keys.sort_unstable();
        return;
    }
    let digit = |k: u64, pass: usize| (k >> (32 + 8 * pass)) as usize & 0xff;
    let mut counts = [[0usize; 256]; 4];
    for &k in keys.iter() {
        for (pass, c) in counts.iter_mut().enumerate() {
            c[digit(k, pass)] += 1;
        }
    }
    let n = keys.len();
    let mut in_tmp = false;
    for (pass, c) in counts.iter().enumerate() {
        if c.contains(&n) {
            continue;
        }
        let mut next = [0usize; 256];
        for d in 1..256 {
            next[d] = next[d - 1] + c[d - 1];
        }
        let (src, dst): (&[u64], &mut [u64]) = if in_tmp { (tmp, keys) } else { (keys, tmp) };
        for &k in src {
            let slot = &mut next[digit(k, pass)];
            dst[*slot] = k;
            *slot += 1;
        }
        in_tmp = !in_tmp;
    }
    if in_tmp {
        keys.copy_from_slice(tmp);
    }
}

/// Split `data` into the disjoint mutable runs `data[offsets[i]..offsets[i + 1]]`.
pub(crate) fn split_by_offsets<'a, T>(mut data: &'a mut [T], offsets: &[usize]) -> Vec<&'a mut [T]> {
    let mut out = Vec::with_capacity(offsets.len().saturating_sub(1));
    for w in offsets.windows(2) {
        let (head, tail) = std::mem::take(&mut data).split_at_mut(w[1] - w[0]);
        out.push(head);
        data = tail;
    }
    out
}

/// For each splat, the positions of its (tile, splat) pairs in `bins.ids`, in tile order: the fixed
/// order in which per-pair gradients are reduced per splat.
pub(crate) fn pairs_by_splat(bins: &Bins, proj: &[Projected]) -> (Vec<usize>, Vec<usize>) {
    let mut offsets = Vec::with_capacity(proj.len() + 1);
    offsets.push(0usize);
    for p in proj {
        offsets.push(offsets.last().unwrap() + p.rect.area());
    }
    let mut cursor = offsets[..proj.len()].to_vec();
    let mut positions = vec![0usize; bins.num_pairs()];
    for (k, &g) in bins.ids.iter().enumerate() {
        let c = &mut cursor[g as usize];
        positions[*c] = k;
        *c += 1;
    }
    (offsets, positions)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raster::project::{Rect, Splat};

    /// Long lists (radix sorted) in the order of a comparison sort of (depth, index).
    #[test]
    fn radix_sort_matches_comparison_sort() {
        let mut state = 7u64;
        let mut keys: Vec<u64> = (0..5000u64)
            .map(|i| {
                state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
                // Few distinct depths, so that ties are common; all in [1, 4).
                let z = 1.0f32 + (state >> 61) as f32 * 0.37 + ((state >> 40) % 3) as f32 * 1e-6;
                (u64::from(z.to_bits()) << 32) | i
            })
            .collect();
        let mut want = keys.clone();
        want.sort_unstable();
        let mut tmp = vec![0; keys.len()];
        sort_by_depth(&mut keys, &mut tmp);
        assert_eq!(keys, want);
    }

    #[test]
    fn depth_order_with_ties_by_index() {
        let full = Rect { x0: 0, x1: 2, y0: 0, y1: 1 };
        let left = Rect { x0: 0, x1: 1, y0: 0, y1: 1 };
        let proj: Vec<Projected> =
            [(full, 2.0), (left, 1.0), (Rect::default(), 0.5), (full, 1.0), (left, 3.0)]
                .iter()
                .map(|&(rect, z)| Projected {
                    splat: Splat { z, ..Default::default() },
                    rect,
                    radius: 1,
                    ..Default::default()
                })
                .collect();
        let bins = bin(&proj, 2, 1);
        assert_eq!(bins.tile(0), &[1, 3, 0, 4]);
        assert_eq!(bins.tile(1), &[3, 0]);
        let (off, pos) = pairs_by_splat(&bins, &proj);
        assert_eq!(off, vec![0, 2, 3, 3, 5, 6]);
        // Splat 0 sits at position 2 (tile 0) and 5 (tile 1); splat 3 at 1 and 4.
        assert_eq!(pos, vec![2, 5, 0, 1, 4, 3]);
    }
}
