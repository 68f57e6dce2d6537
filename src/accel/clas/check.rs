//! The valid-usage rules of the argument records of vkCmdBuildClusterAccelerationStructureIndirectNV
//! that the records themselves (and the objects they name) can break: counts against Arbor's
//! limits and the command's input bounds, index type, strides, truncation range, geometry
//! indices, reserved bits, the kinds of the objects referenced. Each broken rule is a
//! [`Violation`] naming its VUID; the runtime reports it and skips the element.
//!
//! Pure: reads records and blobs handed in, never device memory or diagnostics. Where the
//! specification names no VUID for a bound (the input's per-cluster and total counts), the
//! violation says so (`vuid` is empty) and is reported all the same: the sizes the
//! application allocated were queried with those bounds.
use super::args::{BuildTriangleClusterInfo, BuildTriangleClusterTemplateInfo, GeometryIndexAndFlags, InstantiateClusterInfo};
use super::format::{Blob, Kind};
use super::{MAX_GEOMETRY_INDEX, MAX_TRIANGLES, MAX_VERTICES, TEMPLATE_BOUNDS_ALIGNMENT};

/// VK_BUILD_ACCELERATION_STRUCTURE_ALLOW_CLUSTER_OPACITY_MICROMAPS_BIT_NV.
pub const ALLOW_CLUSTER_OPACITY_MICROMAPS: u32 = 0x1000;

/// One broken rule: its VUID (empty when the specification gives none) and what is wrong.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Violation {
    pub vuid: String,
    pub message: String,
}

fn fail<T>(vuid: &str, message: String) -> Result<T, Violation> {
    Err(Violation { vuid: vuid.to_string(), message })
}

/// The command's input bounds a record is checked against: the triangle-cluster input of the
/// triangle ops and the build flags.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TriangleBounds {
    /// Bytes of one component of the input's vertexFormat (0: not a vertex format Arbor reads).
    pub vertex_component_size: u32,
    pub max_cluster_triangles: u32,
    pub max_cluster_vertices: u32,
    pub min_truncate_bits: u32,
    pub build_flags: u32,
}

/// VUIDs of one rule as the CLAS record and the template record name it.
struct Rule {
    clas: &'static str,
    template: &'static str,
}

macro_rules! rule {
    ($field:literal, $clas:literal, $tpl:literal) => {
        Rule {
            clas: concat!("VUID-VkClusterAccelerationStructureBuildTriangleClusterInfoNV-", $field, "-", $clas),
            template: concat!("VUID-VkClusterAccelerationStructureBuildTriangleClusterTemplateInfoNV-", $field, "-", $tpl),
        }
    };
}

const CLUSTER_ID: Rule = rule!("clusterID", "10488", "10497");
const TRIANGLE_COUNT: Rule = rule!("triangleCount", "10489", "10498");
const VERTEX_COUNT: Rule = rule!("vertexCount", "10490", "10499");
const INDEX_TYPE: Rule = rule!("indexType", "10491", "10500");
const OMM_INDEX_TYPE: Rule = rule!("opacityMicromapIndexType", "10492", "10501");
const TRUNCATE: Rule = rule!("positionTruncateBitCount", "10493", "10502");
const INDEX_STRIDE: Rule = rule!("indexBufferStride", "10494", "10503");
const VERTEX_STRIDE: Rule = rule!("vertexBufferStride", "10495", "10504");
const GEOMETRY_INDEX: Rule = rule!("baseGeometryIndex", "10496", "10506");
const OMM_ARRAY: Rule = rule!("opacityMicromapArray", "10881", "10882");
pub const RESERVED_GEOMETRY_BITS: &str = "VUID-VkClusterAccelerationStructureGeometryIndexAndGeometryFlagsNV-reserved-10487";

// One function: the rules of the record's fields in the specification's order, one each.
/// The rules of a CLAS or template record on its own fields (`template` picks the VUIDs).
pub fn cluster_record(a: &BuildTriangleClusterInfo, template: bool, b: &TriangleBounds) -> Result<(), Violation> {
    let v = |r: &Rule| if template { r.template } else { r.clas };
    if a.cluster_id == u32::MAX {
        return fail(v(&CLUSTER_ID), "clusterID is 0xFFFFFFFF (the value of a hit on no cluster)".into());
    }
    let t = a.triangle_count();
    if t > MAX_TRIANGLES {
        return fail(v(&TRIANGLE_COUNT), format!("triangleCount {t} exceeds maxTrianglesPerCluster {MAX_TRIANGLES}"));
    }
    if a.vertex_count() > MAX_VERTICES {
        return fail(v(&VERTEX_COUNT), format!("vertexCount {} exceeds maxVerticesPerCluster {MAX_VERTICES}", a.vertex_count()));
    }
    let it = a.index_type();
    if !matches!(it, 1 | 2 | 4) {
        return fail(v(&INDEX_TYPE), format!("indexType {it:#x} is not exactly one of the 8-, 16- and 32-bit index format bits"));
    }
    if a.opacity_micromap_array != 0 {
        if b.build_flags & ALLOW_CLUSTER_OPACITY_MICROMAPS == 0 {
            return fail(v(&OMM_ARRAY), "opacityMicromapArray is set but input.flags lacks ALLOW_CLUSTER_OPACITY_MICROMAPS".into());
        }
        // Only checked when a micromap is named: every client leaves the field 0 without one.
        let ot = a.opacity_micromap_index_type();
        if !matches!(ot, 1 | 2 | 4) {
            return fail(v(&OMM_INDEX_TYPE), format!("opacityMicromapIndexType {ot:#x} is not exactly one index format bit"));
        }
    }
    let bits = a.position_truncate_bit_count();
    if bits < b.min_truncate_bits || bits > 32 {
        return fail(v(&TRUNCATE), format!("positionTruncateBitCount {bits} is outside [input.minPositionTruncateBitCount {}, 32]", b.min_truncate_bits));
    }
    if a.index_buffer_stride != 0 && !(a.index_buffer_stride as u32).is_multiple_of(it) {
        return fail(v(&INDEX_STRIDE), format!("indexBufferStride {} is not a multiple of the index size {it}", a.index_buffer_stride));
    }
    // The reading of the KHR rule (03735): a multiple of the format's component size.
    let c = b.vertex_component_size.max(1);
    if a.vertex_buffer_stride != 0 && !(a.vertex_buffer_stride as u32).is_multiple_of(c) {
        return fail(v(&VERTEX_STRIDE), format!("vertexBufferStride {} is not a multiple of the vertex format's component size {c}", a.vertex_buffer_stride));
    }
    let base = a.base_geometry_index_and_geometry_flags;
    if base.reserved() != 0 {
        return fail(RESERVED_GEOMETRY_BITS, format!("baseGeometryIndexAndGeometryFlags has reserved bits {:#x}", base.reserved()));
    }
    if t > b.max_cluster_triangles {
        return fail("", format!("triangleCount {t} exceeds the input's maxClusterTriangleCount {} (the bound the sizes were queried with)", b.max_cluster_triangles));
    }
    if a.vertex_count() > b.max_cluster_vertices {
        return fail("", format!("vertexCount {} exceeds the input's maxClusterVertexCount {}", a.vertex_count(), b.max_cluster_vertices));
    }
    Ok(())
}

/// The geometry words read for a record (one per triangle, or none without a buffer): their
/// reserved bits, and the resolved index against maxClusterGeometryIndex.
pub fn geometry_words(a: &BuildTriangleClusterInfo, template: bool, words: &[u32]) -> Result<(), Violation> {
    let base = a.base_geometry_index_and_geometry_flags;
    let mut highest = base.geometry_index() as u64;
    for (i, &w) in words.iter().enumerate() {
        let w = GeometryIndexAndFlags(w);
        if w.reserved() != 0 {
            return fail(RESERVED_GEOMETRY_BITS, format!("the geometry index and flags word of triangle {i} has reserved bits {:#x}", w.reserved()));
        }
        highest = highest.max(base.geometry_index() as u64 + w.geometry_index() as u64);
    }
    if highest >= MAX_GEOMETRY_INDEX as u64 {
        let vuid = if template { GEOMETRY_INDEX.template } else { GEOMETRY_INDEX.clas };
        return fail(vuid, format!("geometry index {highest} (base plus per-triangle) is not below maxClusterGeometryIndex {MAX_GEOMETRY_INDEX}"));
    }
    Ok(())
}

/// A template record's own rule beyond the CLAS rules (10505).
pub fn template_record(a: &BuildTriangleClusterTemplateInfo) -> Result<(), Violation> {
    let limit = a.instantiation_bounding_box_limit;
    if !limit.is_multiple_of(TEMPLATE_BOUNDS_ALIGNMENT) {
        return fail(
            "VUID-VkClusterAccelerationStructureBuildTriangleClusterTemplateInfoNV-instantiationBoundingBoxLimit-10505",
            format!("instantiationBoundingBoxLimit {limit:#x} is not a multiple of clusterTemplateBoundsByteAlignment {TEMPLATE_BOUNDS_ALIGNMENT}"),
        );
    }
    Ok(())
}

/// An instantiation record against its template: reserved bits (10509), vertices (10507), the
/// vertex format (10508) and the geometry indices after the offset (10510). `format` is the
/// command input's vertexFormat (a VkFormat value).
pub fn instantiation(a: &InstantiateClusterInfo, template: &Blob<'_>, format: i32) -> Result<(), Violation> {
    if a.reserved() != 0 {
        return fail(concat!("VUID-VkClusterAccelerationStructureInstantiateClusterInfoNV-", "reserved-10509"), format!("reserved bits {:#x} are set", a.reserved()));
    }
    let h = template.header;
    if a.vertex_buffer.start_address == 0 && h.has_vertices == 0 {
        return fail(concat!("VUID-VkClusterAccelerationStructureInstantiateClusterInfoNV-", "vertexBuffer-10507"), "vertexBuffer is 0 but the template was built without vertices".into());
    }
    if a.vertex_buffer.start_address != 0 && h.vertex_format != format {
        let msg = format!("the input's vertexFormat {format} differs from the template's {}", h.vertex_format);
        return fail(concat!("VUID-VkClusterAccelerationStructureInstantiateClusterInfoNV-", "vertexBuffer-10508"), msg);
    }
    let offset = a.geometry_index_offset() as i64;
    for i in 0..h.triangle_count {
        let g = GeometryIndexAndFlags(template.word(i)).geometry_index() as i64 + offset;
        if !(0..MAX_GEOMETRY_INDEX as i64).contains(&g) {
            let msg = format!("triangle {i}: geometry index {g} after geometryIndexOffset {offset} is outside [0, maxClusterGeometryIndex {MAX_GEOMETRY_INDEX})");
            return fail(concat!("VUID-VkClusterAccelerationStructureInstantiateClusterInfoNV-", "geometryIndexOffset-10510"), msg);
        }
    }
    Ok(())
}

/// The object a MOVE_OBJECTS source names must be a cluster object of the moved type (10483).
pub fn move_source(kind: Option<Kind>, want: Kind, address: u64) -> Result<(), Violation> {
    if kind != Some(want) {
        return fail(
            "VUID-VkClusterAccelerationStructureMoveObjectsInfoNV-srcAccelerationStructure-10483",
            format!("srcAccelerationStructure {address:#x} holds {} (the move's type is {want:?})", kind.map_or("no cluster object".into(), |k| format!("a {k:?}"))),
        );
    }
    Ok(())
}

/// GET_CLUSTER_TEMPLATE_INDICES needs a template (10833).
pub fn template_source(kind: Option<Kind>, address: u64) -> Result<(), Violation> {
    if kind != Some(Kind::Template) {
        return fail("VUID-VkClusterAccelerationStructureGetTemplateIndicesInfoNV-clusterTemplateAddress-10833", format!("clusterTemplateAddress {address:#x} holds no cluster template"));
    }
    Ok(())
}

/// A cluster BLAS record's stride (10486) and its count against the input's per-structure
/// bound (12323).
pub fn blas_record(count: u32, stride: u32, max_per_blas: u32) -> Result<(), Violation> {
    if stride < 8 {
        return fail(concat!("VUID-VkClusterAccelerationStructureBuildClustersBottomLevelInfoNV-", "clusterReferencesStride-10486"), format!("clusterReferencesStride {stride} is below 8"));
    }
    if count > max_per_blas {
        return fail(
            "VUID-VkClusterAccelerationStructureCommandsInfoNV-input-12323",
            format!("clusterReferencesCount {count} exceeds the input's maxClusterCountPerAccelerationStructure {max_per_blas}"),
        );
    }
    Ok(())
}

/// The references of one cluster BLAS must be distinct (10484).
pub fn unique_references(references: &[u64]) -> Result<(), Violation> {
    let mut sorted = references.to_vec();
    sorted.sort_unstable();
    if let Some(w) = sorted.windows(2).find(|w| w[0] == w[1]) {
        return fail(concat!("VUID-VkClusterAccelerationStructureBuildClustersBottomLevelInfoNV-", "clusterReferences-10484"), format!("cluster reference {:#x} appears twice", w[0]));
    }
    Ok(())
}

impl From<super::ClusterError> for Violation {
    fn from(e: super::ClusterError) -> Self {
        Violation { vuid: String::new(), message: e.to_string() }
    }
}
