//! The PTLAS blob: a header of its own, the persistent state (instance records as written,
//! partition records, sorted member lists), then an embedded top-level structure in the
//! ordinary stored format (`accel::layout`) whose node section is split into the top region
//! and one fixed region per partition. Every offset is relative to the blob start, so the blob
//! is position independent and a byte copy is a valid PTLAS.
//!
//! Owns: the PTLAS header, the state records and where each section lies. Must not touch: the
//! stored format of the embedded structure (that is `accel::layout`'s; this module only places it).
use bytemuck::{Pod, Zeroable};

use super::Input;
use crate::accel::layout::{self as base, HEADER_SIZE, INSTANCE_RECORD_SIZE, NODE_SIZE, RECORD_SIZE, SECTION_ALIGN};

/// "ARPT": not the "ARBR" of a KHR structure, so the ordinary parser refuses a PTLAS and the
/// traversal hook recognises it from its first bytes.
pub const PTLAS_MAGIC: u32 = u32::from_le_bytes(*b"ARPT");
/// Bump whenever the PTLAS layout or its meaning changes.
pub const PTLAS_VERSION: u32 = 1;
const PTLAS_VALID: u32 = 0x5054_4c56;
pub const PTLAS_HEADER_SIZE: usize = 128;
/// Header flag: partition translation enabled (VkPartitionedAccelerationStructureFlagsNV).
pub const FLAG_TRANSLATION: u32 = 1;
/// A partition record's `root` when the partition has no active instance.
pub const NO_ROOT: u32 = u32::MAX;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq, Eq)]
pub struct PtlasHeader {
    pub magic: u32,
    pub version: u32,
    pub valid: u32,
    pub flags: u32,
    /// VkBuildAccelerationStructureFlagsKHR of the build that laid the blob out.
    pub build_flags: u32,
    pub instance_capacity: u32,
    pub partition_capacity: u32,
    pub partition_count: u32,
    pub global_capacity: u32,
    pub top_node_capacity: u32,
    pub partition_node_capacity: u32,
    pub reserved: u32,
    pub used_size: u64,
    pub instances_offset: u64,
    pub partitions_offset: u64,
    pub members_offset: u64,
    pub tlas_offset: u64,
    pub tlas_size: u64,
    pub spare: [u64; 4],
}
const _: () = assert!(std::mem::size_of::<PtlasHeader>() == PTLAS_HEADER_SIZE);

/// One instance slot as last written (transform untranslated), whatever its state.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq)]
pub struct StoredInstance {
    pub transform: [f32; 12],
    pub explicit_aabb: [f32; 6],
    pub instance_id: u32,
    pub mask: u32,
    pub sbt_offset: u32,
    pub flags: u32,
    pub instance_index: u32,
    pub partition_index: u32,
    pub blas: u64,
    /// 1 once a WRITE_INSTANCE named this slot; 0 = never written (a disabled instance).
    pub written: u32,
    pub reserved: u32,
}
pub const STORED_INSTANCE_SIZE: usize = 112;
const _: () = assert!(std::mem::size_of::<StoredInstance>() == STORED_INSTANCE_SIZE);

/// One partition (index `partition_count` is the global partition).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq)]
pub struct PartitionRecord {
    pub translation: [f32; 3],
    pub member_count: u32,
    /// Bounds of the active members (world space, translation applied).
    pub bounds: [f32; 6],
    /// Node index of the partition's root in the embedded structure, or NO_ROOT.
    pub root: u32,
    pub active_count: u32,
    pub node_count: u32,
    /// Half-area of `bounds` when the tree was last rebuilt: refits past a bound of it rebuild.
    pub rebuilt_area: f32,
}
pub const PARTITION_RECORD_SIZE: usize = 56;
const _: () = assert!(std::mem::size_of::<PartitionRecord>() == PARTITION_RECORD_SIZE);

/// The counts a blob is laid out for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Capacities {
    pub instances: u32,
    pub per_partition: u32,
    pub partitions: u32,
    pub global: u32,
    pub translation: bool,
}

impl Capacities {
    pub fn of(input: &Input) -> Capacities {
        Capacities {
            instances: input.instance_count,
            per_partition: input.max_instance_per_partition_count,
            partitions: input.partition_count,
            global: input.max_instance_in_global_partition_count,
            translation: input.translation,
        }
    }
    pub fn of_header(h: &PtlasHeader) -> Capacities {
        Capacities {
            instances: h.instance_capacity,
            per_partition: h.partition_capacity,
            partitions: h.partition_count,
            global: h.global_capacity,
            translation: h.flags & FLAG_TRANSLATION != 0,
        }
    }
    /// Field-wise the larger of two.
    pub fn max(self, o: Capacities) -> Capacities {
        Capacities {
            instances: self.instances.max(o.instances),
            per_partition: self.per_partition.max(o.per_partition),
            partitions: self.partitions.max(o.partitions),
            global: self.global.max(o.global),
            translation: self.translation || o.translation,
        }
    }
}

/// Node bound of the BVH4 `tree::build` makes over n entries: every node has at least two
/// children except a root over one entry (and node 0 always exists in the top region).
pub fn max_nodes(n: u64) -> u64 {
    n.saturating_sub(1).max(1)
}

fn align_up(v: u64) -> u64 {
    v.saturating_add(SECTION_ALIGN - 1) / SECTION_ALIGN * SECTION_ALIGN
}

/// Where every section of a blob with these capacities lies (saturating: absurd counts give
/// u64::MAX sizes rather than wrapping).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Sections {
    pub instances: u64,
    pub partitions: u64,
    pub members: u64,
    pub tlas: u64,
    pub tlas_records: u64,
    pub tlas_instances: u64,
    pub tlas_blas_table: u64,
    pub tlas_nodes: u64,
    pub tlas_size: u64,
    pub top_nodes: u64,
    pub partition_nodes: u64,
    pub end: u64,
}

pub fn sections(c: &Capacities) -> Sections {
    let n = c.instances as u64;
    let p = c.partitions as u64;
    let members = p.saturating_mul(c.per_partition as u64).saturating_add(c.global as u64);
    let top_nodes = max_nodes(p.saturating_add(c.global as u64));
    let partition_nodes = if c.per_partition == 0 { 0 } else { max_nodes(c.per_partition as u64) };
    let mut off = align_up(PTLAS_HEADER_SIZE as u64);
    let mut next = |bytes: u64| {
        let start = off;
        off = align_up(off.saturating_add(bytes));
        start
    };
    let instances = next(n.saturating_mul(STORED_INSTANCE_SIZE as u64));
    let partitions = next(p.saturating_add(1).saturating_mul(PARTITION_RECORD_SIZE as u64));
    let members_off = next(members.saturating_mul(4));
    let tlas = off;
    // The embedded structure: its own offsets are relative to `tlas`.
    let mut toff = align_up(HEADER_SIZE as u64);
    let mut tnext = |bytes: u64| {
        let start = toff;
        toff = align_up(toff.saturating_add(bytes));
        start
    };
    let tlas_records = tnext(n.saturating_mul(RECORD_SIZE as u64));
    let tlas_instances = tnext(n.saturating_mul(INSTANCE_RECORD_SIZE as u64));
    let tlas_blas_table = tnext(n.saturating_mul(8));
    let node_total = top_nodes.saturating_add(p.saturating_mul(partition_nodes));
    let tlas_nodes = tnext(node_total.saturating_mul(NODE_SIZE as u64));
    Sections {
        instances,
        partitions,
        members: members_off,
        tlas,
        tlas_records,
        tlas_instances,
        tlas_blas_table,
        tlas_nodes,
        tlas_size: toff,
        top_nodes,
        partition_nodes,
        end: tlas.saturating_add(toff),
    }
}

pub fn header_for(c: &Capacities, s: &Sections, build_flags: u32) -> PtlasHeader {
    PtlasHeader {
        magic: PTLAS_MAGIC,
        version: PTLAS_VERSION,
        valid: PTLAS_VALID,
        flags: if c.translation { FLAG_TRANSLATION } else { 0 },
        build_flags,
        instance_capacity: c.instances,
        partition_capacity: c.per_partition,
        partition_count: c.partitions,
        global_capacity: c.global,
        top_node_capacity: s.top_nodes as u32,
        partition_node_capacity: s.partition_nodes as u32,
        reserved: 0,
        used_size: s.end,
        instances_offset: s.instances,
        partitions_offset: s.partitions,
        members_offset: s.members,
        tlas_offset: s.tlas,
        tlas_size: s.tlas_size,
        spare: [0; 4],
    }
}

/// The header of a valid PTLAS whose sections all lie inside `bytes` (None otherwise).
pub fn parse(bytes: &[u8]) -> Option<PtlasHeader> {
    parse_header(bytes).filter(|h| h.used_size <= bytes.len() as u64)
}

/// A self-consistent PTLAS header at the start of `bytes` (which may hold the header alone).
pub fn parse_header(bytes: &[u8]) -> Option<PtlasHeader> {
    let h: PtlasHeader = bytemuck::pod_read_unaligned(bytes.get(..PTLAS_HEADER_SIZE)?);
    if h.magic != PTLAS_MAGIC || h.version != PTLAS_VERSION || h.valid != PTLAS_VALID {
        return None;
    }
    // The offsets must be exactly those the capacities give: nothing else was ever written.
    let c = Capacities::of_header(&h);
    let s = sections(&c);
    let ok = s.end == h.used_size
        && s.instances == h.instances_offset
        && s.partitions == h.partitions_offset
        && s.members == h.members_offset
        && s.tlas == h.tlas_offset
        && s.tlas_size == h.tlas_size
        && s.top_nodes == h.top_node_capacity as u64
        && s.partition_nodes == h.partition_node_capacity as u64;
    ok.then_some(h)
}

/// The embedded top-level structure of a valid PTLAS: what traversal walks.
pub fn embedded(bytes: &[u8]) -> Option<&[u8]> {
    let h = parse(bytes)?;
    let start = usize::try_from(h.tlas_offset).ok()?;
    let end = usize::try_from(h.tlas_offset.checked_add(h.tlas_size)?).ok()?;
    let t = bytes.get(start..end)?;
    base::parse(t).map(|_| t)
}

