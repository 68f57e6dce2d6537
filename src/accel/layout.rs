//! The stored format: header, BVH4 nodes with quantised child boxes, primitive data, records,
//! geometry table, instance table, BLAS address table. All offsets are relative to the blob
//! start so clone/compact are byte copies. Everything is `#[repr(C)]` + Pod with size asserts.
use super::params::{EMIT_CUT, PRE_BYTES_PER_PRIM};
use super::{AsType, BuildFlags, BuildSizes, GeometryShape};
use bytemuck::{Pod, Zeroable};

pub const MAGIC: u32 = u32::from_le_bytes(*b"ARBR");
/// Bump whenever any stored layout or its meaning changes (and change ACCEL_FORMAT_UUID).
pub const FORMAT_VERSION: u32 = 4;
const VALID: u32 = 0x5641_4c44;
/// Sections start at multiples of this (keeps nodes cache-line aligned when dst is).
pub const SECTION_ALIGN: u64 = 64;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq)]
pub struct RawHeader {
    pub magic: u32,
    pub version: u32,
    pub ty: u32,
    pub flags: u32,
    pub valid: u32,
    pub geometry_count: u32,
    /// Stored (active) primitives; for a TLAS the stored instances.
    pub primitive_count: u32,
    pub instance_count: u32,
    pub node_count: u32,
    pub leaf_count: u32,
    pub blas_reference_count: u32,
    pub sah_cost: f32,
    pub bounds: [f32; 6],
    /// Primitive IDs consumed, inactive ones included (sum of primitive counts).
    pub total_primitives: u32,
    /// Slots in the BLAS address table (= stored instances: one reference per stored instance).
    pub blas_table_capacity: u32,
    pub used_size: u64,
    pub nodes_offset: u64,
    pub prims_offset: u64,
    pub records_offset: u64,
    pub geometries_offset: u64,
    pub instances_offset: u64,
    pub blas_table_offset: u64,
    pub max_leaf_size: u32,
    pub reserved: u32,
    /// `checksum::structure_checksum` of the finished structure (this field counted as 0, the
    /// BLAS table left out): copies and deserialization verify it.
    pub checksum: u64,
    pub spare: u64,
}
pub const HEADER_SIZE: usize = 160;
const _: () = assert!(std::mem::size_of::<RawHeader>() == HEADER_SIZE);

/// Child slot `prim_count[i]`: 0 = empty slot, LEAF_INTERNAL = internal node, else leaf size.
pub const CHILD_INTERNAL: u8 = 0xff;

/// A BVH4 node: 4 child boxes quantised to 8 bits per plane in the frame
/// origin + q * 2^(exp-127), rounded outward at encode time so traversal is conservative.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq)]
pub struct WideNode {
    pub origin: [f32; 3],
    pub exp: [u8; 3],
    pub child_count: u8,
    /// [axis][child]
    pub qlo: [[u8; 4]; 3],
    pub qhi: [[u8; 4]; 3],
    /// Internal child: node index. Leaf child: first primitive slot.
    pub child: [u32; 4],
    /// 0 = unused slot, CHILD_INTERNAL = internal node, 1..=254 = leaf with that many primitives.
    pub kind: [u8; 4],
    pub reserved: u32,
}
pub const NODE_SIZE: usize = 64;
const _: () = assert!(std::mem::size_of::<WideNode>() == NODE_SIZE);

impl WideNode {
    pub fn scale(&self, axis: usize) -> f32 {
        f32::from_bits((self.exp[axis] as u32) << 23)
    }
    /// The conservative box of child `c` (the exact same arithmetic the encoder verified).
    pub fn child_box(&self, c: usize) -> [f32; 6] {
        let mut b = [0f32; 6];
        for a in 0..3 {
            let s = self.scale(a);
            b[a] = self.origin[a] + self.qlo[a][c] as f32 * s;
            b[a + 3] = self.origin[a] + self.qhi[a][c] as f32 * s;
        }
        b
    }
}

/// Precomputed triangle vertices (or an AABB in the first six floats) of one stored primitive.
pub type PrimData = [f32; 9];
pub const PRIM_SIZE: usize = 36;

/// Which input primitive sits in a stored slot (for hits, refit and validation).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq, Eq)]
pub struct PrimRecord {
    pub geometry: u32,
    pub primitive: u32,
}
pub const RECORD_SIZE: usize = 8;
const _: () = assert!(std::mem::size_of::<PrimRecord>() == RECORD_SIZE);

pub const KIND_TRIANGLES: u32 = 0;
pub const KIND_AABBS: u32 = 1;
pub const KIND_INSTANCES: u32 = 2;

/// Header `ty` values of the cluster blobs (`accel::clas`, docs/CLUSTERS.md), which share the
/// magic word: `parse` refuses them, `clas::open` accepts only them.
pub const KIND_CLAS: u32 = 0x10;
pub const KIND_CLUSTER_TEMPLATE: u32 = 0x11;
pub const KIND_CLUSTER_BLAS: u32 = 0x12;

/// Per-geometry facts traversal (flags) and update checks (everything else) need.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq, Eq)]
pub struct GeometryRecord {
    pub kind: u32,
    pub flags: u32,
    pub primitive_count: u32,
    pub active_count: u32,
    pub format: i32,
    pub index_type: i32,
    pub max_vertex: u32,
    pub has_transform: u32,
    /// FNV-1a of the index bytes (only with ALLOW_UPDATE; else 0): the update's index check.
    pub index_hash: [u32; 2],
}
pub const GEOMETRY_SIZE: usize = 40;
const _: () = assert!(std::mem::size_of::<GeometryRecord>() == GEOMETRY_SIZE);

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq)]
pub struct InstanceRecord {
    pub object_to_world: [f32; 12],
    pub world_to_object: [f32; 12],
    pub custom_index: u32,
    pub mask: u32,
    pub sbt_offset: u32,
    pub flags: u32,
    /// InstanceId: index in the build's instance array.
    pub instance_index: u32,
    /// Index into the BLAS address table.
    pub blas_index: u32,
}
pub const INSTANCE_RECORD_SIZE: usize = 120;
const _: () = assert!(std::mem::size_of::<InstanceRecord>() == INSTANCE_RECORD_SIZE);

/// Public view of a header.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Header {
    pub ty: AsType,
    pub flags: BuildFlags,
    pub used_size: u64,
    pub geometry_count: u32,
    /// Stored (active) primitives; for a TLAS the stored (active) instances.
    pub primitive_count: u32,
    pub instance_count: u32,
    pub node_count: u32,
    pub leaf_count: u32,
    pub bounds: [f32; 6],
    pub blas_reference_count: u32,
    pub sah_cost: f32,
}

fn align_up(v: u64) -> u64 {
    v.saturating_add(SECTION_ALIGN - 1) / SECTION_ALIGN * SECTION_ALIGN
}

/// Section offsets of a structure with these counts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Sections {
    pub nodes: u64,
    pub prims: u64,
    pub records: u64,
    pub geometries: u64,
    pub instances: u64,
    pub blas_table: u64,
    pub end: u64,
}

/// Offsets for counts given in u64 (saturating: a size query with absurd counts gives u64::MAX).
pub fn sections(ty: AsType, nodes: u64, prims: u64, geometries: u64) -> Sections {
    let tri = ty == AsType::BottomLevel;
    let mut off = align_up(HEADER_SIZE as u64);
    let mut next = |bytes: u64| {
        let start = off;
        off = align_up(off.saturating_add(bytes));
        start
    };
    // Nodes come last: every other offset is then independent of the tree, so the builder
    // fills the tables before the node count is known and emits nodes in one pass.
    let geo_off = next(geometries.saturating_mul(GEOMETRY_SIZE as u64));
    let prims_off = next(if tri { prims.saturating_mul(PRIM_SIZE as u64) } else { 0 });
    let records_off = next(prims.saturating_mul(RECORD_SIZE as u64));
    let inst_off = next(if tri { 0 } else { prims.saturating_mul(INSTANCE_RECORD_SIZE as u64) });
    let blas_off = next(if tri { 0 } else { prims.saturating_mul(8) });
    let nodes_off = next(nodes.saturating_mul(NODE_SIZE as u64));
    Sections { nodes: nodes_off, prims: prims_off, records: records_off, geometries: geo_off, instances: inst_off, blas_table: blas_off, end: off }
}

/// Worst-case wide node count for n stored primitives, for any binary tree the builder can
/// make (leaves of at least one primitive) collapsed by `tree::wide_children` (derivation in
/// docs/ACCEL_API.md, "Sizes"): a wide node of fewer than four children has only leaves and
/// cut roots below it, which caps the count at (2L - 1 + K) / 3 for L <= n leaves and
/// K <= 3·floor(n / (EMIT_CUT + 1)) cut roots under such nodes; a root leaf takes one node.
pub fn max_nodes(n: u64) -> u64 {
    max_nodes_with_leaves(n, n)
}

/// `max_nodes` for trees of at most `leaves` leaves over n primitives.
pub fn max_nodes_with_leaves(n: u64, leaves: u64) -> u64 {
    if n == 0 {
        return 0;
    }
    let cut_children = 3 * (n / (EMIT_CUT as u64 + 1));
    // A size query's n may be near u64::MAX (saturated sums); such sizes saturate anyway.
    let leaves = leaves.clamp(1, n).min(u64::MAX / 4);
    ((2 * leaves - 1 + cut_children) / 3).max(1)
}

/// Whether the builder keeps at least two primitives in every leaf of a tree of two or more
/// (`subtree::BuildContext::pair_leaves`): BLAS builds of the PREFER_FAST_BUILD tier (the
/// tier of `BuildParams::from_flags`: PREFER_FAST_TRACE wins). Their trees have at most
/// floor(n / 2) leaves, which the size query counts on.
pub fn pairs_leaves(ty: AsType, flags: BuildFlags) -> bool {
    ty == AsType::BottomLevel && flags.contains(BuildFlags::PREFER_FAST_BUILD) && !flags.contains(BuildFlags::PREFER_FAST_TRACE)
}

/// Worst-case wide nodes of a build of `n` primitives with these type and flags.
pub fn max_nodes_for(ty: AsType, flags: BuildFlags, n: u64) -> u64 {
    if pairs_leaves(ty, flags) {
        max_nodes_with_leaves(n, n / 2)
    } else {
        max_nodes(n)
    }
}

/// The size query's acceleration-structure size: every section at its worst case. Nothing
/// else lives in dst during a build (the staging area is in scratch).
pub fn structure_size_bound(ty: AsType, flags: BuildFlags, n: u64, geometries: u64) -> u64 {
    let s = sections(ty, max_nodes_for(ty, flags, n), n, geometries);
    s.end
}

pub const SCRATCH_SLACK: u64 = 64;
pub const PRIMREF_SIZE: u64 = 32;
pub const BINNODE_SIZE: u64 = 40;
/// Bytes of a build's staging record: the primitive data the format stores (PRIM_SIZE) and
/// the primitive's index in its geometry, at the global ID in scratch (BLAS builds).
pub const STAGE_SIZE: usize = 40;

pub fn build_scratch_size(ty: AsType, n: u64) -> u64 {
    // Primitive references, then up to 2n binary nodes (slot scheme: a subtree over k
    // primitives owns 2k-1 consecutive slots), then n + 1 words for the primitives per
    // reference of clustered builds, then the pre-emission area (PRE_BYTES_PER_PRIM per
    // primitive: cut roots encoded while the tree is built), then for a BLAS the staging area
    // (STAGE_SIZE per primitive, read back by the leaf-order pass), each region aligned.
    let stage = if ty == AsType::BottomLevel { SCRATCH_SLACK.saturating_add(n.saturating_mul(STAGE_SIZE as u64)) } else { 0 };
    SCRATCH_SLACK
        .saturating_add(n.saturating_mul(PRIMREF_SIZE))
        .saturating_add(SCRATCH_SLACK)
        .saturating_add(n.saturating_mul(2).saturating_mul(BINNODE_SIZE))
        .saturating_add(SCRATCH_SLACK)
        .saturating_add(n.saturating_add(1).saturating_mul(4))
        .saturating_add(SCRATCH_SLACK)
        .saturating_add(n.saturating_mul(PRE_BYTES_PER_PRIM as u64))
        .saturating_add(stage)
}

pub fn update_scratch_size(ty: AsType, n: u64) -> u64 {
    // A TLAS sorts one 8-byte key per instance and keeps each instance's new box (24 bytes) for
    // the node pass, two aligned arrays; a BLAS refits in place, node boxes subtree by subtree
    // in registers, and uses no scratch (the slack keeps the size non-zero, a buffer to bind).
    if ty == AsType::TopLevel {
        SCRATCH_SLACK.saturating_add(n.saturating_mul(32))
    } else {
        SCRATCH_SLACK
    }
}

/// Sizes for the size query. Only the node section depends on the flags: PREFER_FAST_BUILD
/// BLAS trees pair their leaves (`pairs_leaves`); none of ALLOW_UPDATE, ALLOW_COMPACTION or
/// ALLOW_DATA_ACCESS stores anything more.
pub fn build_sizes(ty: AsType, flags: BuildFlags, shapes: &[GeometryShape], max_primitive_counts: &[u32]) -> BuildSizes {
    let n: u64 = shapes
        .iter()
        .enumerate()
        .map(|(i, _)| max_primitive_counts.get(i).copied().unwrap_or(0) as u64)
        .fold(0u64, |a, b| a.saturating_add(b));
    let size = structure_size_bound(ty, flags, n, shapes.len() as u64);
    BuildSizes { acceleration_structure_size: size, build_scratch_size: build_scratch_size(ty, n), update_scratch_size: update_scratch_size(ty, n) }
}

/// A validated header with the section slices it promises.
#[derive(Clone, Copy, Debug)]
pub struct Parsed<'a> {
    pub raw: RawHeader,
    pub bytes: &'a [u8],
}

fn read_raw(bytes: &[u8]) -> Option<RawHeader> {
    let b = bytes.get(..HEADER_SIZE)?;
    Some(bytemuck::pod_read_unaligned(b))
}

pub fn parse(bytes: &[u8]) -> Option<Parsed<'_>> {
    let raw = read_raw(bytes)?;
    if raw.magic != MAGIC || raw.version != FORMAT_VERSION || raw.valid != VALID || raw.ty > 1 {
        return None;
    }
    if raw.used_size > bytes.len() as u64 {
        return None;
    }
    let used = raw.used_size;
    let fits = |off: u64, count: u32, size: usize| off.checked_add(count as u64 * size as u64).is_some_and(|e| e <= used) && off >= HEADER_SIZE as u64;
    let tlas = raw.ty == AsType::TopLevel as u32;
    let ok = fits(raw.nodes_offset, raw.node_count, NODE_SIZE)
        && (tlas || fits(raw.prims_offset, raw.primitive_count, PRIM_SIZE))
        && fits(raw.records_offset, raw.primitive_count, RECORD_SIZE)
        && fits(raw.geometries_offset, raw.geometry_count, GEOMETRY_SIZE)
        && (!tlas || fits(raw.instances_offset, raw.instance_count, INSTANCE_RECORD_SIZE))
        && (!tlas || fits(raw.blas_table_offset, raw.blas_table_capacity, 8))
        && raw.blas_reference_count <= raw.blas_table_capacity
        && (!tlas || raw.instance_count == raw.primitive_count);
    if !ok {
        return None;
    }
    Some(Parsed { raw, bytes: &bytes[..used as usize] })
}

impl<'a> Parsed<'a> {
    pub fn is_tlas(&self) -> bool {
        self.raw.ty == AsType::TopLevel as u32
    }
    pub fn node(&self, i: u32) -> Option<WideNode> {
        if i >= self.raw.node_count {
            return None;
        }
        let off = self.raw.nodes_offset as usize + i as usize * NODE_SIZE;
        Some(bytemuck::pod_read_unaligned(self.bytes.get(off..off + NODE_SIZE)?))
    }
    pub fn prim(&self, i: u32) -> Option<PrimData> {
        if i >= self.raw.primitive_count || self.is_tlas() {
            return None;
        }
        let off = self.raw.prims_offset as usize + i as usize * PRIM_SIZE;
        Some(bytemuck::pod_read_unaligned(self.bytes.get(off..off + PRIM_SIZE)?))
    }
    pub fn record(&self, i: u32) -> Option<PrimRecord> {
        if i >= self.raw.primitive_count {
            return None;
        }
        let off = self.raw.records_offset as usize + i as usize * RECORD_SIZE;
        Some(bytemuck::pod_read_unaligned(self.bytes.get(off..off + RECORD_SIZE)?))
    }
    pub fn geometry(&self, i: u32) -> Option<GeometryRecord> {
        if i >= self.raw.geometry_count {
            return None;
        }
        let off = self.raw.geometries_offset as usize + i as usize * GEOMETRY_SIZE;
        Some(bytemuck::pod_read_unaligned(self.bytes.get(off..off + GEOMETRY_SIZE)?))
    }
    pub fn instance(&self, i: u32) -> Option<InstanceRecord> {
        if i >= self.raw.instance_count || !self.is_tlas() {
            return None;
        }
        let off = self.raw.instances_offset as usize + i as usize * INSTANCE_RECORD_SIZE;
        Some(bytemuck::pod_read_unaligned(self.bytes.get(off..off + INSTANCE_RECORD_SIZE)?))
    }
    pub fn blas_address(&self, i: u32) -> Option<u64> {
        if i >= self.raw.blas_reference_count {
            return None;
        }
        let off = self.raw.blas_table_offset as usize + i as usize * 8;
        Some(bytemuck::pod_read_unaligned(self.bytes.get(off..off + 8)?))
    }
}

pub fn write_header(dst: &mut [u8], raw: &RawHeader) -> bool {
    match dst.get_mut(..HEADER_SIZE) {
        Some(d) => {
            d.copy_from_slice(bytemuck::bytes_of(raw));
            true
        }
        None => false,
    }
}

pub fn valid_word() -> u32 {
    VALID
}

/// Traversal of a structure marked invalid finds nothing; header() returns None.
pub fn mark_invalid(dst: &mut [u8]) {
    // Clearing magic and valid word is enough: parse() checks both (the checksum goes too).
    let n = dst.len().min(HEADER_SIZE);
    for b in dst[..n].iter_mut() {
        *b = 0;
    }
}

/// None if not a valid Arbor structure.
pub fn header(bytes: &[u8]) -> Option<Header> {
    // A cluster BLAS answers with its embedded BVH's header: instances may name it.
    let (p, side) = super::clas::open_walkable(bytes)?;
    let r = p.raw;
    let used_size = if side.is_some() { super::clas::open(bytes)?.header.used_size } else { r.used_size };
    Some(Header {
        ty: if r.ty == 0 { AsType::TopLevel } else { AsType::BottomLevel },
        flags: BuildFlags(r.flags),
        used_size,
        geometry_count: r.geometry_count,
        primitive_count: r.primitive_count,
        instance_count: r.instance_count,
        node_count: r.node_count,
        leaf_count: r.leaf_count,
        bounds: r.bounds,
        blas_reference_count: r.blas_reference_count,
        sah_cost: r.sah_cost,
    })
}

/// Splits an aligned array of `count` T off the front of scratch bytes (no unsafe: skip to an
/// aligned offset, then let bytemuck check alignment and size).
pub fn carve<T: Pod>(bytes: &mut [u8], count: usize) -> Option<(&mut [T], &mut [u8])> {
    let align = std::mem::align_of::<T>().max(16);
    let addr = bytes.as_ptr() as usize;
    let skip = (align - addr % align) % align;
    let size = count.checked_mul(std::mem::size_of::<T>())?;
    let end = skip.checked_add(size)?;
    if end > bytes.len() {
        return None;
    }
    let (head, rest) = bytes.split_at_mut(end);
    let arr: &mut [T] = bytemuck::try_cast_slice_mut(&mut head[skip..]).ok()?;
    Some((arr, rest))
}

