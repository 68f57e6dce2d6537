//! Verification of a stored structure that comes from an untrusted source (serialized data, a
//! structure the application may have written over): the header, the section offsets the
//! counts imply, the checksum, the counts of the tables against each other, every record, and
//! the node tree (each node reached once, in preorder, child links in bounds and after their
//! parent, leaves covering every stored primitive exactly once, in order).
//!
//! Owns: the verdict and its reason. Must not touch: anything it checks (it only reads). Nodes
//! are stored in preorder, so one depth-first walk with a stack checks the links without
//! marking nodes; leaves are not stored in walk order, so covered primitives are marked in a
//! bitmap (one bit per stored primitive: host memory of n/8 bytes, only while checking).
use super::checksum;
use super::layout::{self, Parsed, RawHeader, CHILD_INTERNAL, HEADER_SIZE};
use super::{AsType, IndexType, VertexFormat};

/// Why a structure was rejected: a fixed name per check (for diagnostics and counting).
pub type Reason = &'static str;

fn raw_header(bytes: &[u8]) -> Result<RawHeader, Reason> {
    let b = bytes.get(..HEADER_SIZE).ok_or("truncated header")?;
    let raw: RawHeader = bytemuck::pod_read_unaligned(b);
    if raw.magic != layout::MAGIC || raw.version != layout::FORMAT_VERSION {
        return Err("not an Arbor structure of this format version");
    }
    if raw.valid != layout::valid_word() {
        return Err("structure marked invalid");
    }
    if raw.ty > 1 {
        return Err("structure type");
    }
    Ok(raw)
}

/// Counts of the header against each other and the offsets they imply.
fn check_counts(r: &RawHeader) -> Result<(), Reason> {
    let tlas = r.ty == AsType::TopLevel as u32;
    let ty = if tlas { AsType::TopLevel } else { AsType::BottomLevel };
    let s = layout::sections(ty, r.node_count as u64, r.primitive_count as u64, r.geometry_count as u64);
    let offsets = [s.nodes, s.prims, s.records, s.geometries, s.instances, s.blas_table, s.end];
    let stored = [r.nodes_offset, r.prims_offset, r.records_offset, r.geometries_offset, r.instances_offset, r.blas_table_offset, r.used_size];
    if offsets != stored {
        return Err("section offsets");
    }
    let table = if tlas { r.primitive_count } else { 0 };
    if r.instance_count != table || r.blas_table_capacity != table || r.blas_reference_count != table {
        return Err("instance and BLAS-table counts");
    }
    if (r.node_count == 0) != (r.primitive_count == 0) || r.leaf_count > r.node_count.saturating_mul(4) || r.leaf_count > r.primitive_count {
        return Err("node and leaf counts");
    }
    if (r.primitive_count as u64) > r.total_primitives as u64 {
        return Err("primitive counts");
    }
    Ok(())
}

/// The geometry table: kinds fit the structure type, formats are known,
/// and the per-geometry counts add up to the header's.
fn check_geometries(p: &Parsed) -> Result<(), Reason> {
    let (mut active, mut total) = (0u64, 0u64);
    for i in 0..p.raw.geometry_count {
        let g = p.geometry(i).ok_or("geometry table")?;
        let kind_ok = if p.is_tlas() { g.kind == layout::KIND_INSTANCES } else { g.kind <= layout::KIND_AABBS };
        if !kind_ok || g.has_transform > 1 || g.active_count > g.primitive_count {
            return Err("geometry record");
        }
        if g.kind == layout::KIND_TRIANGLES && (VertexFormat::from_vk(g.format).is_none() || IndexType::from_vk(g.index_type).is_none()) {
            return Err("geometry record");
        }
        active += g.active_count as u64;
        total += g.primitive_count as u64;
    }
    if active != p.raw.primitive_count as u64 || total != p.raw.total_primitives as u64 {
        return Err("geometry counts");
    }
    Ok(())
}

/// Every stored slot's record names a primitive of its geometry; a TLAS's instance records are
/// well-formed (their fields in the ranges the instance format allows, their BLAS-table index in
/// the table, the same instance as the record).
fn check_records(p: &Parsed) -> Result<(), Reason> {
    for s in 0..p.raw.primitive_count {
        let rec = p.record(s).ok_or("record")?;
        let g = p.geometry(rec.geometry).ok_or("record geometry")?;
        if rec.primitive >= g.primitive_count {
            return Err("record primitive");
        }
        if p.is_tlas() {
            let inst = p.instance(s).ok_or("instance record")?;
            let fields_ok = inst.mask <= 0xFF && inst.custom_index <= 0xFF_FFFF && inst.sbt_offset <= 0xFF_FFFF && inst.flags <= 0xFF;
            if !fields_ok || inst.instance_index != rec.primitive || inst.blas_index >= p.raw.blas_table_capacity {
                return Err("instance record");
            }
        }
    }
    Ok(())
}

/// One depth-first walk in child-slot order: node i must be the i-th node reached (preorder,
/// so each is reached exactly once and no link can form a cycle), and every stored primitive
/// must be in exactly one leaf.
fn check_tree(p: &Parsed) -> Result<(), Reason> {
    #[derive(Clone, Copy)]
    enum Item {
        Node(u32),
        Leaf(u32, u32),
    }
    let r = p.raw;
    let (mut next_node, mut covered, mut leaves) = (0u32, 0u32, 0u32);
    let mut seen = vec![0u64; (r.primitive_count as usize).div_ceil(64)];
    let mut stack: Vec<Item> = Vec::new();
    if r.node_count > 0 {
        stack.push(Item::Node(0));
    }
    while let Some(item) = stack.pop() {
        let i = match item {
            Item::Leaf(first, count) => {
                let end = first.checked_add(count).filter(|&e| e <= r.primitive_count).ok_or("leaf range")?;
                for s in first..end {
                    let (w, b) = ((s / 64) as usize, 1u64 << (s % 64));
                    if seen[w] & b != 0 {
                        return Err("primitive in two leaves");
                    }
                    seen[w] |= b;
                }
                covered += count;
                leaves += 1;
                continue;
            }
            Item::Node(i) => i,
        };
        if i != next_node {
            return Err("node order");
        }
        next_node += 1;
        let n = p.node(i).ok_or("node link")?;
        let count = n.child_count as usize;
        if count == 0 || count > 4 {
            return Err("node child count");
        }
        if n.kind[count..].iter().any(|&k| k != 0) || n.kind[..count].contains(&0) {
            return Err("node child slots");
        }
        // A valid tree never holds more than three pending siblings per level below the root.
        if stack.len() as u64 + 4 > 4 * r.node_count as u64 + 4 {
            return Err("node link");
        }
        for c in (0..count).rev() {
            stack.push(match n.kind[c] {
                CHILD_INTERNAL if n.child[c] <= i || n.child[c] >= r.node_count => return Err("node link"),
                CHILD_INTERNAL => Item::Node(n.child[c]),
                k => Item::Leaf(n.child[c], k as u32),
            });
        }
    }
    if next_node != r.node_count {
        return Err("unreachable node");
    }
    if covered != r.primitive_count || leaves != r.leaf_count {
        return Err("leaf coverage");
    }
    Ok(())
}

/// The integrity verdict: header, counts, sections and checksum. Bytes that pass were written
/// by Arbor's builder, refit or a checked copy and not changed since (the checksum is parallel
/// and cheap); what only passes this may still be forged with a recomputed checksum, which is
/// why data from outside the device (deserialization) gets the whole `check`.
pub fn check_integrity(bytes: &[u8]) -> Result<Parsed<'_>, Reason> {
    let raw = raw_header(bytes)?;
    check_counts(&raw)?;
    let p = layout::parse(bytes).ok_or("sections")?;
    if !checksum::verify(&p.raw, p.bytes) {
        return Err("checksum");
    }
    Ok(p)
}

/// The whole verdict: integrity, then the structure itself (records, tree links, leaf
/// coverage); Ok with the parsed structure, or the first check that failed.
pub fn check(bytes: &[u8]) -> Result<Parsed<'_>, Reason> {
    let p = check_integrity(bytes)?;
    check_geometries(&p)?;
    check_records(&p)?;
    check_tree(&p)?;
    Ok(p)
}
