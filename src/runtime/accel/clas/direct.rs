//! IMPLICIT-mode results written straight into dstImplicitData: CLAS builds, instantiations and
//! moves are placed from their exact sizes first (measured by a sizes-only pass), then made in
//! parallel each into its own slice of one claimed region; a cluster BLAS is built into the
//! room its size bound needs at its place. This spares a zeroed host allocation and a copy
//! per result. The placement, the bytes and what is reported are those of the copying path.
//!
//! A destination must not be read by the command while it is written: when a buffer the
//! elements read (records, indices, geometry words, vertices, templates, CLASes) shares
//! memory with the destination, the copying path runs instead (so overlapping moves, whose
//! sources must all be read before any destination is written, take it).
use rayon::prelude::*;

use super::{report, write, Addresses, ClusterCommand, DeviceInputs, Element};
use crate::accel::clas::args::{AddressInfo, BuildTriangleClusterInfo, InstantiateClusterInfo, OpType};
use crate::accel::clas::check::Violation;
use crate::accel::clas::{self, ClusterError};
use crate::memory::region::Region;
use crate::memory::AddressSpace;

/// Backing memory of a region: (allocation identity, start, end).
type Span = (usize, u64, u64);

/// Whether the whole buffer holding `address` shares memory with `dst` (never for 0 or an
/// unresolvable address, which no read can reach either). Asked per element on every worker:
/// the view answers from buffers this thread already resolved, taking no lock.
fn shares(view: &DeviceInputs<'_>, dst: Span, address: u64) -> bool {
    address != 0 && view.view.buffer_memory(address).is_some_and(|m| m.0 == dst.0 && m.1 < dst.2 && dst.1 < m.2)
}

fn no_fit(i: usize, end: u64) {
    let message = format!("its result does not fit in dstImplicitData (the elements' results pass {end:#x})");
    report(Some(i as u64), &Violation { vuid: String::new(), message });
}

impl ClusterCommand {
    /// Writes the results of an IMPLICIT CLAS build, instantiation, move or cluster BLAS build in
    /// place, with their addresses and sizes. False when nothing was written and the copying
    /// path must run (a destination shares memory with an input).
    pub(super) fn write_in_place(&self, space: &AddressSpace, view: &DeviceInputs<'_>, elements: &mut [Option<Element>], a: &Addresses) -> bool {
        let end = a.implicit.saturating_add(self.implicit_extent(space, a.implicit));
        if self.op == OpType::BuildClustersBottomLevel {
            self.blas_in_place(space, view, elements, a, end);
            return true;
        }
        let mut next = a.implicit;
        let mut at = vec![None; elements.len()];
        for (i, slot) in elements.iter_mut().enumerate() {
            let Some(e) = slot else { continue };
            let p = next.next_multiple_of(self.alignment());
            if p.saturating_add(e.size) > end {
                no_fit(i, end);
                *slot = None;
                continue;
            }
            at[i] = Some(p);
            next = p + e.size;
        }
        let span = next - a.implicit;
        if span == 0 {
            return true;
        }
        let Ok(r) = space.resolve(a.implicit, span) else { return false };
        let Some(dst) = r.buffer.memory_range(r.offset, span) else { return false };
        if shares(view, dst, a.src) || (0..elements.len()).into_par_iter().any(|i| at[i].is_some() && self.element_shares(view, a, i, dst)) {
            return false;
        }
        let Ok(region) = Region::of_device(space, a.implicit, span) else { return false };
        let results: Vec<(usize, Result<(), Violation>)> = region.write_with(|bytes| {
            let (mut rest, mut base) = (bytes, a.implicit);
            let mut jobs = Vec::new();
            for (i, p) in at.iter().enumerate() {
                let (Some(p), Some(e)) = (*p, &elements[i]) else { continue };
                let (_, tail) = std::mem::take(&mut rest).split_at_mut((p - base) as usize);
                let (mine, tail) = tail.split_at_mut(e.size as usize);
                (rest, base) = (tail, p + e.size);
                jobs.push((i, mine));
            }
            jobs.into_par_iter().map(|(i, dst)| (i, self.record(view, a.src, i as u64).and_then(|rec| self.make_one(view, rec, dst)))).collect()
        });
        let mut made = Vec::with_capacity(results.len());
        for (i, result) in results {
            match result {
                Ok(()) => made.push((i, at[i].unwrap_or(0), elements[i].as_ref().map_or(0, |e| e.size))),
                Err(v) => report(Some(i as u64), &v),
            }
        }
        self.write_addresses_and_sizes(space, a, &made);
        true
    }

    /// The addresses and sizes of the elements `made` (index, address, size), each array
    /// written through one region where it is addressable as a whole and the two do not
    /// overlap (then the order of the writes cannot matter), else element by element as
    /// `write_address_and_size` does, which reports what it cannot write.
    fn write_addresses_and_sizes(&self, space: &AddressSpace, a: &Addresses, made: &[(usize, u64, u64)]) {
        let (Some(&(first, ..)), Some(&(last, ..))) = (made.first(), made.last()) else { return };
        let extent = |base: u64, stride: u64, n: u64| -> Option<(u64, u64)> {
            let start = base.checked_add((first as u64).checked_mul(stride)?)?;
            Some((start, ((last - first) as u64).checked_mul(stride)?.checked_add(n)?))
        };
        let arrays = [(a.dst_addresses, self.dst_addresses.stride, 8u64), (a.dst_sizes, self.dst_sizes.stride, 4)];
        let spans: Vec<Option<(u64, u64)>> = arrays.iter().map(|&(base, stride, n)| if base == 0 { Some((0, 0)) } else { extent(base, stride, n) }).collect();
        let disjoint = match (spans[0], spans[1]) {
            (Some(x), Some(y)) => !super::overlaps(x.0, x.1, y.0, y.1),
            _ => false,
        };
        let regions: Vec<Option<Region<'_>>> = spans.iter().map(|s| s.filter(|s| s.1 > 0).and_then(|(at, n)| Region::of_device(space, at, n).ok())).collect();
        let whole = |k: usize| spans[k].is_some_and(|s| s.1 == 0) || regions[k].is_some();
        if !disjoint || !whole(0) || !whole(1) {
            for &(i, at, size) in made {
                self.write_address_and_size(space, a, i, at, size);
            }
            return;
        }
        for (k, region) in regions.into_iter().enumerate() {
            let Some(region) = region else { continue };
            let stride = arrays[k].1 as usize;
            region.write_with(|bytes| {
                for &(i, at, size) in made {
                    let o = (i - first) * stride;
                    if k == 0 {
                        bytes[o..o + 8].copy_from_slice(&at.to_le_bytes());
                    } else {
                        bytes[o..o + 4].copy_from_slice(&(size.min(u32::MAX as u64) as u32).to_le_bytes());
                    }
                }
            });
        }
    }

    /// Whether a buffer element `i` reads shares memory with the destination `dst`.
    fn element_shares(&self, view: &DeviceInputs<'_>, a: &Addresses, i: usize, dst: Span) -> bool {
        let Ok(rec) = self.record(view, a.src, i as u64) else { return false };
        let addresses: [u64; 3] = match self.op {
            OpType::BuildTriangleCluster => {
                let r: BuildTriangleClusterInfo = bytemuck::pod_read_unaligned(rec);
                [r.index_buffer, r.geometry_index_and_flags_buffer, r.vertex_buffer]
            }
            OpType::InstantiateTriangleCluster => {
                let r: InstantiateClusterInfo = bytemuck::pod_read_unaligned(rec);
                [r.cluster_template_address, r.vertex_buffer.start_address, 0]
            }
            OpType::MoveObjects => [bytemuck::pod_read_unaligned::<AddressInfo>(rec).address, 0, 0],
            _ => [0; 3],
        };
        addresses.into_iter().any(|x| shares(view, dst, x))
    }

    /// One CLAS (built or instantiated) or moved object into `dst`, which holds exactly its size.
    fn make_one(&self, view: &DeviceInputs<'_>, rec: &[u8], dst: &mut [u8]) -> Result<(), Violation> {
        match self.op {
            OpType::MoveObjects => {
                let r: AddressInfo = bytemuck::pod_read_unaligned(rec);
                let src = Self::object(view, r.address)?;
                let n = dst.len();
                dst.copy_from_slice(src.get(..n).ok_or(ClusterError::Unreadable { what: "srcAccelerationStructure", address: r.address })?);
            }
            OpType::BuildTriangleCluster => {
                let r: BuildTriangleClusterInfo = bytemuck::pod_read_unaligned(rec);
                let format = self.vertex_format.ok_or(ClusterError::NotA("supported vertex format"))?;
                clas::build_clas(&r, format, view, dst)?;
            }
            _ => {
                let r: InstantiateClusterInfo = bytemuck::pod_read_unaligned(rec);
                let tpl = Self::object(view, r.cluster_template_address)?;
                clas::instantiate(tpl, &r, view, dst)?;
            }
        }
        Ok(())
    }

    fn write_address_and_size(&self, space: &AddressSpace, a: &Addresses, i: usize, at: u64, size: u64) {
        let i = i as u64;
        if a.dst_addresses != 0 {
            write(space, a.dst_addresses.wrapping_add(i * self.dst_addresses.stride), &at.to_le_bytes());
        }
        if a.dst_sizes != 0 {
            write(space, a.dst_sizes.wrapping_add(i * self.dst_sizes.stride), &(size.min(u32::MAX as u64) as u32).to_le_bytes());
        }
    }

    /// Cluster BLASes in order, each built where its bound fits and no CLAS it reads shares its
    /// room's memory, else made in host memory and copied (the copying path's rule: what
    /// counts is its used size).
    fn blas_in_place(&self, space: &AddressSpace, view: &DeviceInputs<'_>, elements: &[Option<Element>], a: &Addresses, end: u64) {
        let mut next = a.implicit;
        for (i, slot) in elements.iter().enumerate() {
            let Some(e) = slot else { continue };
            let p = next.next_multiple_of(self.alignment());
            let built = self.record(view, a.src, i as u64).and_then(|rec| match self.blas_into(space, view, rec, (a.src, p), e.size, end) {
                Some(r) => r,
                None => self.produce(view, rec, false).map(|e| {
                    let bytes = e.bytes.unwrap_or_default();
                    if p.saturating_add(e.size) > end || !write(space, p, &bytes) {
                        0
                    } else {
                        e.size
                    }
                }),
            });
            match built {
                Ok(0) => no_fit(i, end),
                Ok(used) => {
                    next = p + used;
                    self.write_address_and_size(space, a, i, p, used);
                }
                Err(v) => report(Some(i as u64), &v),
            }
        }
    }

    /// One cluster BLAS built at `p` when its `bound` fits before `end` and none of its inputs
    /// (the records at `src` included) shares memory with it; None to take the copying path.
    fn blas_into(&self, space: &AddressSpace, view: &DeviceInputs<'_>, rec: &[u8], (src, p): (u64, u64), bound: u64, end: u64) -> Option<Result<u64, Violation>> {
        if p.saturating_add(bound) > end {
            return None;
        }
        let r = space.resolve(p, bound).ok()?;
        let dst = r.buffer.memory_range(r.offset, bound)?;
        let info: crate::accel::clas::args::BuildClustersBottomLevelInfo = bytemuck::pod_read_unaligned(rec);
        let clusters = match self.blas_clusters(view, &info) {
            Ok(c) => c,
            Err(v) => return Some(Err(v)),
        };
        if shares(view, dst, src) || shares(view, dst, info.cluster_references) || clusters.par_iter().any(|c| shares(view, dst, c.0)) {
            return None;
        }
        let region = Region::of_device(space, p, bound).ok()?;
        Some(region.write_with(|bytes| Ok(clas::build_cluster_blas(&clusters, self.build_flags, bytes)?)))
    }
}
