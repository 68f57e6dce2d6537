//! vkCmdBuildClusterAccelerationStructureIndirectNV as the runtime runs it: the recorded
//! [`ClusterCommand`] resolves its address indirections, checks the command's valid-usage
//! rules, reads the element count and the argument records from device memory when the queue
//! executes it, checks each record, makes every result in host memory (`accel::clas`), then
//! writes results, addresses and sizes by mode. Making every result before writing any is what
//! lets a move's destinations overlap other moves' sources. In IMPLICIT mode results are made
//! straight in dstImplicitData instead where no input shares its memory (`direct`).
//!
//! Owns the execution model of nv-extensions.md B.6 and the valid-usage checks of the command
//! (docs/CLUSTERS.md lists them); the rules of one record are `accel::clas::check`'s, the blob
//! formats `accel::clas`'s. A broken command-wide rule skips the command; a failing element is
//! reported and skipped while the others complete. Usage-flag mismatches are reported as
//! warnings and the command runs (public clients commit them).
use ash::vk;
use rayon::prelude::*;

use super::inputs::DeviceInputs;
use crate::accel::clas::args::{AddressInfo, BuildClustersBottomLevelInfo, BuildTriangleClusterInfo, BuildTriangleClusterTemplateInfo, InstantiateClusterInfo, ObjectType, OpMode, OpType};
use crate::accel::clas::check::{self, TriangleBounds, Violation};
use crate::accel::clas::{self, ClusterError, Kind};
use crate::accel::{DeviceView, VertexFormat};
use crate::diag;
use crate::memory::region::Region;
use crate::memory::AddressSpace;
use crate::runtime::command::{Exec, ExecContext, ExecError};
use crate::runtime::in_use::Collector;

mod direct;
#[cfg(test)]
mod tests;

const CMD: &str = "vkCmdBuildClusterAccelerationStructureIndirectNV";

fn cmd_vuid(rule: &str) -> String {
    format!("VUID-{CMD}-{rule}")
}

fn info_vuid(rule: &str) -> String {
    format!("VUID-VkClusterAccelerationStructureCommandsInfoNV-{rule}")
}

/// VkStridedDeviceAddressRegionKHR, copied at record time.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Strided {
    pub address: u64,
    pub stride: u64,
    pub size: u64,
}

/// VkClusterAccelerationStructureAddressResolutionFlagBitsNV.
pub mod resolution {
    pub const DST_IMPLICIT_DATA: u32 = 0x01;
    pub const SCRATCH_DATA: u32 = 0x02;
    pub const DST_ADDRESS_ARRAY: u32 = 0x04;
    pub const DST_SIZES_ARRAY: u32 = 0x08;
    pub const SRC_INFOS_ARRAY: u32 = 0x10;
    pub const SRC_INFOS_COUNT: u32 = 0x20;
}

/// The op input's bounds as the application gave them to the command (and, for the memory it
/// allocated, to the size query).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct InputBounds {
    /// Triangle ops: the input's vertexFormat (a VkFormat value).
    pub vertex_format: i32,
    pub max_cluster_triangles: u32,
    pub max_cluster_vertices: u32,
    pub max_total_triangles: u32,
    pub max_total_vertices: u32,
    pub min_truncate_bits: u32,
    /// BUILD_CLUSTERS_BOTTOM_LEVEL.
    pub max_total_clusters: u32,
    pub max_clusters_per_blas: u32,
    /// MOVE_OBJECTS.
    pub max_moved_bytes: u64,
}

/// The lowered VkClusterAccelerationStructureCommandsInfoNV (with its op input).
#[derive(Clone, Debug)]
pub struct ClusterCommand {
    pub op: OpType,
    pub mode: OpMode,
    pub max_count: u32,
    pub build_flags: u32,
    /// Triangle ops: the input's vertexFormat (None: not an accepted vertex format).
    pub vertex_format: Option<VertexFormat>,
    /// MOVE_OBJECTS: the type moved.
    pub move_type: ObjectType,
    pub dst_implicit_data: u64,
    pub scratch_data: u64,
    pub dst_addresses: Strided,
    pub dst_sizes: Strided,
    pub src_infos: Strided,
    pub src_infos_count: u64,
    pub address_resolution: u32,
    pub bounds: InputBounds,
    /// accelerationStructureSize of the size query for the same input: what dstImplicitData
    /// must hold in IMPLICIT mode.
    pub queried_size: u64,
}

fn read_u64(view: &DeviceInputs<'_>, address: u64) -> Option<u64> {
    view.bytes(address, 8).map(|b| u64::from_le_bytes(b.try_into().unwrap_or([0; 8])))
}

fn write(space: &AddressSpace, address: u64, data: &[u8]) -> bool {
    match Region::of_device(space, address, data.len() as u64) {
        Ok(r) => {
            r.write_with(|b| b.copy_from_slice(data));
            true
        }
        Err(e) => {
            diag::report(diag::Level::Error, CMD, &format!("cannot write {} bytes at {address:#x}: {e}", data.len()));
            false
        }
    }
}

/// Bytes from `address` to the end of the buffer holding it (0 when none does).
fn room(space: &AddressSpace, address: u64) -> u64 {
    space.resolve(address, 1).map_or(0, |r| r.buffer.size - r.offset)
}

fn overlaps(a: u64, alen: u64, b: u64, blen: u64) -> bool {
    alen > 0 && blen > 0 && a < b.saturating_add(blen) && b < a.saturating_add(alen)
}

/// Reports one element's (or, without an index, the command's) violation.
fn report(element: Option<u64>, v: &Violation) {
    let message = match element {
        Some(i) => format!("element {i}: {}; nothing written for it", v.message),
        None => v.message.clone(),
    };
    if v.vuid.is_empty() {
        diag::report(diag::Level::Error, CMD, &message);
    } else {
        diag::vuid(&v.vuid, CMD, &message);
    }
}

/// A usage-flag mismatch: reported, not enforced (public clients commit them, nv-usage.md).
fn check_usage(space: &AddressSpace, address: u64, usage: vk::BufferUsageFlags, rule: &str, what: &str) {
    if address == 0 {
        return;
    }
    if let Ok(found) = space.buffer_usage_at(address, 1) {
        if !found.contains(usage) {
            let message = format!("[{}] {what} lies in a buffer without {usage:?} (has {found:?}); the command runs", cmd_vuid(rule));
            diag::report(diag::Level::Warn, CMD, &message);
        }
    }
}

/// The extension enabled without its feature struct in vkCreateDevice's chain: reported as a
/// warning, and the command runs. The Khronos validation layer of Vulkan header 239 drops the
/// structs it does not know from that chain, so an application tested under it cannot enable
/// the feature; a struct that says VK_FALSE is enforced.
pub fn feature_struct_missing(vuid: &str, command: &str) {
    let message = format!("[{vuid}] VK_NV_cluster_acceleration_structure is enabled without VkPhysicalDeviceClusterAccelerationStructureFeaturesNV in the device's chain; the command runs");
    diag::report(diag::Level::Warn, command, &message);
}

/// What one element produced: its result bytes (None in COMPUTE_SIZES mode), its size, and
/// what it counts against the input's totals (triangles and vertices, clusters, or bytes moved).
struct Element {
    bytes: Option<Vec<u8>>,
    size: u64,
    tally: [u64; 2],
}
type Produced = Result<Element, Violation>;

/// The command's addresses after their INDIRECTED bits.
#[derive(Clone, Copy, Debug, Default)]
struct Addresses {
    src: u64,
    count_at: u64,
    dst_addresses: u64,
    dst_sizes: u64,
    implicit: u64,
    scratch: u64,
}

impl ClusterCommand {
    /// A field after its INDIRECTED bit: the address read there, or the field itself.
    fn resolve(&self, view: &DeviceInputs<'_>, bit: u32, field: u64) -> Option<u64> {
        if self.address_resolution & bit == 0 || field == 0 {
            return Some(field);
        }
        let a = read_u64(view, field);
        if a.is_none() {
            diag::report(diag::Level::Error, CMD, &format!("the indirected address at {field:#x} is unreadable; command skipped"));
        }
        a
    }

    fn resolve_all(&self, view: &DeviceInputs<'_>) -> Option<Addresses> {
        let r = |bit, field| self.resolve(view, bit, field);
        Some(Addresses {
            src: r(resolution::SRC_INFOS_ARRAY, self.src_infos.address)?,
            count_at: r(resolution::SRC_INFOS_COUNT, self.src_infos_count)?,
            dst_addresses: r(resolution::DST_ADDRESS_ARRAY, self.dst_addresses.address)?,
            dst_sizes: r(resolution::DST_SIZES_ARRAY, self.dst_sizes.address)?,
            implicit: r(resolution::DST_IMPLICIT_DATA, self.dst_implicit_data)?,
            scratch: r(resolution::SCRATCH_DATA, self.scratch_data)?,
        })
    }

    fn alignment(&self) -> u64 {
        match self.op {
            OpType::BuildTriangleCluster | OpType::InstantiateTriangleCluster => clas::CLAS_ALIGNMENT,
            OpType::BuildTriangleClusterTemplate => clas::TEMPLATE_ALIGNMENT,
            OpType::BuildClustersBottomLevel => clas::BLAS_ALIGNMENT,
            OpType::GetClusterTemplateIndices => 4,
            OpType::MoveObjects => match self.move_type {
                ObjectType::ClustersBottomLevel => clas::BLAS_ALIGNMENT,
                ObjectType::TriangleCluster => clas::CLAS_ALIGNMENT,
                ObjectType::TriangleClusterTemplate => clas::TEMPLATE_ALIGNMENT,
            },
        }
    }

    /// The destination-alignment rule of the op (12317-12319 name the triangle ops, 12316 the
    /// others); None for the template indices, whose results have no alignment property.
    fn alignment_rule(&self) -> Option<&'static str> {
        match self.op {
            OpType::BuildTriangleCluster => Some("input-12317"),
            OpType::BuildTriangleClusterTemplate => Some("input-12318"),
            OpType::InstantiateTriangleCluster => Some("input-12319"),
            OpType::BuildClustersBottomLevel | OpType::MoveObjects => Some("opMode-12316"),
            OpType::GetClusterTemplateIndices => None,
        }
    }

    fn is_triangle_op(&self) -> bool {
        !matches!(self.op, OpType::MoveObjects | OpType::BuildClustersBottomLevel)
    }

    fn triangle_bounds(&self) -> TriangleBounds {
        TriangleBounds {
            vertex_component_size: self.vertex_format.map_or(0, |f| f.component_size()),
            max_cluster_triangles: self.bounds.max_cluster_triangles,
            max_cluster_vertices: self.bounds.max_cluster_vertices,
            min_truncate_bits: self.bounds.min_truncate_bits,
            build_flags: self.build_flags,
        }
    }

    fn record_stride(&self) -> u64 {
        if self.src_infos.stride == 0 {
            self.op.record_size()
        } else {
            self.src_infos.stride
        }
    }

    /// Element `i`'s argument record.
    fn record<'v>(&self, view: &'v DeviceInputs<'_>, src: u64, i: u64) -> Result<&'v [u8], Violation> {
        let address = src.wrapping_add(i * self.record_stride());
        let size = self.op.record_size();
        Ok(view.bytes(address, size).ok_or(ClusterError::Unreadable { what: "srcInfosArray element", address })?)
    }

    /// The per-triangle geometry words of a record (none without a buffer), checked (10487,
    /// 10496 / 10506).
    fn check_geometry_words(&self, view: &DeviceInputs<'_>, a: &BuildTriangleClusterInfo, template: bool) -> Result<(), Violation> {
        let mut words = Vec::new();
        if a.geometry_index_and_flags_buffer != 0 {
            let stride = if a.geometry_index_and_flags_buffer_stride == 0 { 4 } else { a.geometry_index_and_flags_buffer_stride as u64 };
            for i in 0..a.triangle_count() as u64 {
                let at = a.geometry_index_and_flags_buffer.wrapping_add(i * stride);
                let b = view.bytes(at, 4).ok_or(ClusterError::Unreadable { what: "geometry index and flags", address: at })?;
                words.push(u32::from_le_bytes([b[0], b[1], b[2], b[3]]));
            }
        }
        check::geometry_words(a, template, &words)
    }

    /// The cluster object at `address`.
    fn object<'v>(view: &'v DeviceInputs<'_>, address: u64) -> Result<&'v [u8], Violation> {
        Ok(view.acceleration_structure(address).ok_or(ClusterError::Unreadable { what: "cluster object", address })?)
    }

    // One function: one arm per op type, each checking its record, sizing and building.
    /// Element `rec`'s result: its size and tally only when `sizes_only`, else also its bytes.
    fn produce(&self, view: &DeviceInputs<'_>, rec: &[u8], sizes_only: bool) -> Produced {
        let format = || self.vertex_format.ok_or(ClusterError::NotA("supported vertex format"));
        let alloc = |n: u64| vec![0u8; n as usize];
        let bounds = self.triangle_bounds();
        match self.op {
            OpType::BuildTriangleCluster => {
                let a: BuildTriangleClusterInfo = bytemuck::pod_read_unaligned(rec);
                check::cluster_record(&a, false, &bounds)?;
                self.check_geometry_words(view, &a, false)?;
                let size = clas::clas_size(a.triangle_count() as u64);
                let tally = [a.triangle_count() as u64, a.vertex_count() as u64];
                if sizes_only {
                    return Ok(Element { bytes: None, size, tally });
                }
                let mut dst = alloc(size);
                clas::build_clas(&a, format()?, view, &mut dst)?;
                Ok(Element { bytes: Some(dst), size, tally })
            }
            OpType::BuildTriangleClusterTemplate => {
                let a: BuildTriangleClusterTemplateInfo = bytemuck::pod_read_unaligned(rec);
                check::cluster_record(&a.cluster, true, &bounds)?;
                check::template_record(&a)?;
                self.check_geometry_words(view, &a.cluster, true)?;
                let size = clas::template_size(a.cluster.triangle_count() as u64, a.cluster.vertex_buffer != 0);
                let tally = [a.cluster.triangle_count() as u64, a.cluster.vertex_count() as u64];
                if sizes_only {
                    return Ok(Element { bytes: None, size, tally });
                }
                let limit = match a.instantiation_bounding_box_limit {
                    0 => None,
                    at => {
                        let b = view.bytes(at, 24).ok_or(ClusterError::Unreadable { what: "instantiationBoundingBoxLimit", address: at })?;
                        Some(std::array::from_fn(|k| f32::from_le_bytes(b[4 * k..4 * k + 4].try_into().unwrap_or([0; 4]))))
                    }
                };
                let mut dst = alloc(size);
                clas::build_template(&a.cluster, format()?, limit, view, &mut dst)?;
                Ok(Element { bytes: Some(dst), size, tally })
            }
            OpType::InstantiateTriangleCluster => {
                let a: InstantiateClusterInfo = bytemuck::pod_read_unaligned(rec);
                let tpl = Self::object(view, a.cluster_template_address)?;
                let blob = clas::open(tpl).filter(|b| b.kind == Kind::Template).ok_or(ClusterError::NotA("cluster template"))?;
                check::instantiation(&a, &blob, self.bounds.vertex_format)?;
                let (t, v) = (blob.header.triangle_count, blob.header.vertex_count);
                if t > bounds.max_cluster_triangles {
                    let message = format!("the template's {t} triangles exceed the input's maxClusterTriangleCount {}", bounds.max_cluster_triangles);
                    return Err(Violation { vuid: String::new(), message });
                }
                // A CLAS's size depends on its triangle count only: exact even without vertices.
                let size = clas::clas_size(t as u64);
                if sizes_only {
                    return Ok(Element { bytes: None, size, tally: [t as u64, v as u64] });
                }
                let mut dst = alloc(size);
                clas::instantiate(tpl, &a, view, &mut dst)?;
                Ok(Element { bytes: Some(dst), size, tally: [t as u64, v as u64] })
            }
            OpType::BuildClustersBottomLevel => self.produce_blas(view, rec, sizes_only),
            OpType::MoveObjects => {
                let a: AddressInfo = bytemuck::pod_read_unaligned(rec);
                let bytes = Self::object(view, a.address).map_err(|_| ClusterError::Unreadable { what: "srcAccelerationStructure", address: a.address })?;
                let found = clas::object_size(bytes);
                let want = match self.move_type {
                    ObjectType::ClustersBottomLevel => Kind::ClusterBlas,
                    ObjectType::TriangleCluster => Kind::Clas,
                    ObjectType::TriangleClusterTemplate => Kind::Template,
                };
                check::move_source(found.map(|f| f.0), want, a.address)?;
                let size = found.map_or(0, |f| f.1);
                Ok(Element { bytes: (!sizes_only).then(|| bytes[..size as usize].to_vec()), size, tally: [size, 0] })
            }
            OpType::GetClusterTemplateIndices => {
                let a: AddressInfo = bytemuck::pod_read_unaligned(rec);
                let tpl = Self::object(view, a.address).map_err(|_| ClusterError::Unreadable { what: "clusterTemplateAddress", address: a.address })?;
                check::template_source(clas::object_size(tpl).map(|f| f.0), a.address)?;
                let size = clas::template_indices_size(tpl)?;
                if sizes_only {
                    return Ok(Element { bytes: None, size, tally: [0, 0] });
                }
                let mut dst = alloc(size);
                clas::template_indices(tpl, &mut dst)?;
                Ok(Element { bytes: Some(dst), size, tally: [0, 0] })
            }
        }
    }

    /// A cluster BLAS record's CLASes (address and bytes, in reference order), checked.
    fn blas_clusters<'v>(&self, view: &'v DeviceInputs<'_>, a: &BuildClustersBottomLevelInfo) -> Result<Vec<(u64, &'v [u8])>, Violation> {
        check::blas_record(a.cluster_references_count, a.cluster_references_stride, self.bounds.max_clusters_per_blas)?;
        let stride = a.cluster_references_stride as u64;
        let mut addresses = Vec::with_capacity(a.cluster_references_count as usize);
        for k in 0..a.cluster_references_count as u64 {
            let at = a.cluster_references.wrapping_add(k * stride);
            let Some(address) = read_u64(view, at) else {
                let message = format!("clusterReferences holds no reference {k} at {at:#x} (clusterReferencesCount {})", a.cluster_references_count);
                return Err(Violation { vuid: "VUID-VkClusterAccelerationStructureBuildClustersBottomLevelInfoNV-clusterReferences-10485".into(), message });
            };
            addresses.push(address);
        }
        check::unique_references(&addresses)?;
        let mut clusters = Vec::with_capacity(addresses.len());
        for &address in &addresses {
            clusters.push((address, Self::object(view, address).map_err(|_| ClusterError::NotAClas { address })?));
        }
        Ok(clusters)
    }

    /// The size bound of a cluster BLAS over `clusters` (what its build needs to write into).
    fn blas_bound(clusters: &[(u64, &[u8])]) -> u64 {
        let triangles: u64 = clusters.iter().map(|c| clas::open(c.1).map_or(0, |b| b.header.triangle_count as u64)).sum();
        clas::blas_size_for(clusters.len() as u64, triangles)
    }

    fn produce_blas(&self, view: &DeviceInputs<'_>, rec: &[u8], sizes_only: bool) -> Produced {
        let a: BuildClustersBottomLevelInfo = bytemuck::pod_read_unaligned(rec);
        let clusters = self.blas_clusters(view, &a)?;
        let bound = Self::blas_bound(&clusters);
        let tally = [clusters.len() as u64, 0];
        if sizes_only {
            return Ok(Element { bytes: None, size: bound, tally });
        }
        let mut dst = vec![0u8; bound as usize];
        let used = clas::build_cluster_blas(&clusters, self.build_flags, &mut dst)?;
        dst.truncate(used as usize);
        Ok(Element { bytes: Some(dst), size: used, tally })
    }

    /// The rules on the op input itself (10439-10442): a broken one skips the command.
    fn check_input(&self) -> bool {
        if !self.is_triangle_op() {
            return true;
        }
        let b = &self.bounds;
        let input = "VUID-VkClusterAccelerationStructureTriangleClusterInputNV-";
        let broken = if self.vertex_format.is_none() {
            Some((format!("{input}vertexFormat-10439"), format!("vertexFormat {} lacks ACCELERATION_STRUCTURE_VERTEX_BUFFER", b.vertex_format)))
        } else if b.max_cluster_triangles > clas::MAX_TRIANGLES {
            Some((format!("{input}maxClusterTriangleCount-10440"), format!("maxClusterTriangleCount {} exceeds maxTrianglesPerCluster {}", b.max_cluster_triangles, clas::MAX_TRIANGLES)))
        } else if b.max_cluster_vertices > clas::MAX_VERTICES {
            Some((format!("{input}maxClusterVertexCount-10441"), format!("maxClusterVertexCount {} exceeds maxVerticesPerCluster {}", b.max_cluster_vertices, clas::MAX_VERTICES)))
        } else if b.min_truncate_bits > 32 {
            Some((format!("{input}minPositionTruncateBitCount-10442"), format!("minPositionTruncateBitCount {} exceeds 32", b.min_truncate_bits)))
        } else {
            None
        };
        if let Some((vuid, message)) = &broken {
            diag::vuid(vuid, CMD, &format!("{message}; command skipped"));
        }
        broken.is_none()
    }

    // One function: the command-wide rules in the order of the specification's lists.
    /// The command-wide rules on the resolved addresses; false when the command must be skipped.
    /// The scratch rules are reported and not enforced: Arbor's working arrays live in host
    /// memory and it never writes scratch.
    fn check_command(&self, space: &AddressSpace, a: &Addresses) -> bool {
        let mut skip = Vec::new();
        if a.dst_addresses != 0 && self.dst_addresses.stride < 8 {
            skip.push((info_vuid("dstAddressesArray-10474"), format!("dstAddressesArray.stride {} is below 8", self.dst_addresses.stride)));
        }
        if a.dst_sizes != 0 && self.dst_sizes.stride < 4 {
            skip.push((info_vuid("dstSizesArray-10475"), format!("dstSizesArray.stride {} is below 4", self.dst_sizes.stride)));
        }
        if self.src_infos.stride != 0 && self.src_infos.stride < self.op.record_size() {
            let message = format!("srcInfosArray.stride {} is below the {} bytes of one argument record", self.src_infos.stride, self.op.record_size());
            skip.push((info_vuid("srcInfosArray-10476"), message));
        }
        match self.mode {
            OpMode::ImplicitDestinations if a.implicit == 0 => skip.push((info_vuid("opMode-12309"), "IMPLICIT mode with dstImplicitData 0".into())),
            OpMode::ExplicitDestinations if a.dst_addresses == 0 => skip.push((info_vuid("opMode-12313"), "EXPLICIT mode with dstAddressesArray 0".into())),
            OpMode::ComputeSizes if a.dst_sizes == 0 => skip.push((info_vuid("opMode-12312"), "COMPUTE_SIZES mode with dstSizesArray 0".into())),
            _ => {}
        }
        if self.mode == OpMode::ImplicitDestinations && a.implicit != 0 {
            if let Some(rule) = self.alignment_rule().filter(|r| r.starts_with("input-") && !a.implicit.is_multiple_of(self.alignment())) {
                skip.push((info_vuid(rule), format!("dstImplicitData {:#x} is not a multiple of the op's alignment {}", a.implicit, self.alignment())));
            }
            let have = room(space, a.implicit);
            if self.op != OpType::MoveObjects && have < self.queried_size {
                let message = format!("dstImplicitData {:#x} holds {have} bytes; the size query for this input gives {}", a.implicit, self.queried_size);
                skip.push((info_vuid("opMode-12310"), message));
            }
            if overlaps(a.implicit, self.implicit_extent(space, a.implicit), a.scratch, clas::SCRATCH_SIZE) {
                skip.push((cmd_vuid("dstImplicitData-10456"), "dstImplicitData overlaps scratchData".into()));
            }
        }
        if !a.count_at.is_multiple_of(4) {
            skip.push((info_vuid("srcInfosCount-12322"), format!("srcInfosCount {:#x} is not 4-byte aligned", a.count_at)));
        }
        self.check_scratch(space, a.scratch);
        check_usage(space, a.scratch, vk::BufferUsageFlags::STORAGE_BUFFER, "pCommandInfos-10457", "scratchData");
        let read_only = vk::BufferUsageFlags::ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_KHR;
        check_usage(space, a.src, read_only, "pCommandInfos-10458", "srcInfosArray");
        check_usage(space, a.count_at, read_only, "pCommandInfos-10458", "srcInfosCount");
        let storage = vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR;
        if self.mode == OpMode::ImplicitDestinations {
            check_usage(space, a.implicit, storage, "pCommandInfos-10459", "dstImplicitData");
        }
        check_usage(space, a.dst_addresses, storage, "pCommandInfos-10459", "dstAddressesArray");
        for (vuid, message) in &skip {
            diag::vuid(vuid, CMD, &format!("{message}; command skipped"));
        }
        skip.is_empty()
    }

    /// The bytes of dstImplicitData the command may write: what the size query gave (moves:
    /// to the end of the buffer, their rule being the sum of the moved sizes).
    fn implicit_extent(&self, space: &AddressSpace, implicit: u64) -> u64 {
        let have = room(space, implicit);
        if self.op == OpType::MoveObjects {
            have
        } else {
            have.min(self.queried_size)
        }
    }

    /// The scratch rules (10446, 10447, 12321): reported, and the command still runs.
    fn check_scratch(&self, space: &AddressSpace, scratch: u64) {
        if scratch == 0 {
            diag::vuid(&info_vuid("buildScratchSize-12321"), CMD, &format!("scratchData is 0; the queried scratch size is {}", clas::SCRATCH_SIZE));
            return;
        }
        if !scratch.is_multiple_of(clas::SCRATCH_ALIGNMENT) {
            let message = format!("scratchData {scratch:#x} is not a multiple of clusterScratchByteAlignment ({})", clas::SCRATCH_ALIGNMENT);
            diag::vuid(&cmd_vuid("scratchData-10447"), CMD, &message);
        }
        if let Err(e) = Region::of_device(space, scratch, clas::SCRATCH_SIZE) {
            let message = format!("scratchData {scratch:#x} does not hold the queried scratch size ({} bytes): {e}", clas::SCRATCH_SIZE);
            diag::vuid(&cmd_vuid("scratchData-10446"), CMD, &message);
        }
    }

    /// The element count: srcInfosCount's value (10453: at most maxAccelerationStructureCount),
    /// and no more records than srcInfosArray.size holds (10454).
    fn count(&self, view: &DeviceInputs<'_>, count_at: u64) -> Option<u64> {
        let mut count = match count_at {
            0 => self.max_count,
            at => {
                let Some(b) = view.bytes(at, 4) else {
                    diag::report(diag::Level::Error, CMD, &format!("srcInfosCount {at:#x} is unreadable; command skipped"));
                    return None;
                };
                let n = u32::from_le_bytes(b.try_into().unwrap_or([0; 4]));
                if n > self.max_count {
                    let message = format!("srcInfosCount holds {n}, above input.maxAccelerationStructureCount {}; the first {} run", self.max_count, self.max_count);
                    diag::vuid(&cmd_vuid("pCommandInfos-10453"), CMD, &message);
                }
                n.min(self.max_count)
            }
        } as u64;
        let (stride, size) = (self.record_stride(), self.op.record_size());
        let fit = if self.src_infos.size < size { 0 } else { (self.src_infos.size - size) / stride + 1 };
        if count > fit {
            let message = format!("srcInfosArray.size {} holds {fit} records of the {count} to run; the rest are skipped", self.src_infos.size);
            diag::vuid(&cmd_vuid("pCommandInfos-10454"), CMD, &message);
            count = fit;
        }
        Some(count)
    }

    /// The input's totals over the elements in order: an element that would pass one is
    /// reported and skipped.
    fn check_totals(&self, elements: &mut [Option<Element>]) {
        let b = &self.bounds;
        let (limits, vuid, what): ([u64; 2], &'static str, [&str; 2]) = match self.op {
            OpType::BuildTriangleCluster | OpType::BuildTriangleClusterTemplate | OpType::InstantiateTriangleCluster => {
                ([b.max_total_triangles as u64, b.max_total_vertices as u64], "", ["maxTotalTriangleCount", "maxTotalVertexCount"])
            }
            OpType::BuildClustersBottomLevel => ([b.max_total_clusters as u64, u64::MAX], "VUID-VkClusterAccelerationStructureCommandsInfoNV-input-12323", ["maxTotalClusterCount", ""]),
            OpType::MoveObjects => ([b.max_moved_bytes, u64::MAX], "VUID-VkClusterAccelerationStructureCommandsInfoNV-input-10469", ["maxMovedBytes", ""]),
            OpType::GetClusterTemplateIndices => return,
        };
        let mut sum = [0u64; 2];
        for (i, slot) in elements.iter_mut().enumerate() {
            let Some(e) = slot else { continue };
            let next = [sum[0] + e.tally[0], sum[1] + e.tally[1]];
            if let Some(k) = (0..2).find(|&k| next[k] > limits[k]) {
                let message = format!("the elements up to {i} total {} against the input's {} {}", next[k], what[k], limits[k]);
                report(Some(i as u64), &Violation { vuid: vuid.to_string(), message });
                *slot = None;
                continue;
            }
            sum = next;
        }
    }

    fn run(&self, space: &AddressSpace) {
        if !self.check_input() {
            return;
        }
        let view = DeviceInputs::new(space, CMD);
        let Some(a) = self.resolve_all(&view) else { return };
        if !self.check_command(space, &a) {
            return;
        }
        let Some(count) = self.count(&view, a.count_at) else { return };
        // IMPLICIT builds measure first and write in place (direct.rs); the others make bytes.
        let in_place = self.mode == OpMode::ImplicitDestinations && self.op != OpType::GetClusterTemplateIndices && self.op != OpType::BuildTriangleClusterTemplate;
        let sizes_only = in_place || self.mode == OpMode::ComputeSizes;
        let produced: Vec<Produced> = (0..count).into_par_iter().map(|i| self.record(&view, a.src, i).and_then(|rec| self.produce(&view, rec, sizes_only))).collect();
        let mut elements: Vec<Option<Element>> = produced
            .into_iter()
            .enumerate()
            .map(|(i, p)| p.map_err(|v| report(Some(i as u64), &v)).ok())
            .collect();
        self.check_totals(&mut elements);
        if self.mode == OpMode::ImplicitDestinations && self.op == OpType::MoveObjects {
            let moved: u64 = elements.iter().flatten().map(|e| e.size).sum();
            let have = room(space, a.implicit);
            if have < moved {
                let message = format!("dstImplicitData {:#x} holds {have} bytes; the moved objects take {moved}; command skipped", a.implicit);
                diag::vuid(&info_vuid("opMode-12311"), CMD, &message);
                return;
            }
        }
        if in_place {
            if self.write_in_place(space, &view, &mut elements, &a) {
                return;
            }
            elements = elements
                .into_par_iter()
                .enumerate()
                .map(|(i, e)| e.and_then(|_| self.record(&view, a.src, i as u64).and_then(|rec| self.produce(&view, rec, false)).map_err(|v| report(Some(i as u64), &v)).ok()))
                .collect();
        }
        self.write_outputs(space, &view, elements, &a);
    }

    /// Where element `i`'s result goes in EXPLICIT mode, checked: alignment (12316-12319), room
    /// (12314), and overlap with scratch (10455) and with earlier destinations (12315).
    fn explicit_destination(&self, space: &AddressSpace, view: &DeviceInputs<'_>, a: &Addresses, i: u64, size: u64, taken: &[(u64, u64)]) -> Result<u64, Violation> {
        let stride = self.dst_addresses.stride;
        let Some(at) = read_u64(view, a.dst_addresses.wrapping_add(i * stride)) else {
            return Err(Violation { vuid: String::new(), message: "its dstAddressesArray entry is unreadable".into() });
        };
        if let Some(rule) = self.alignment_rule().filter(|_| !at.is_multiple_of(self.alignment())) {
            let message = format!("destination {at:#x} is not a multiple of the op's alignment {}", self.alignment());
            return Err(Violation { vuid: info_vuid(rule), message });
        }
        let have = room(space, at);
        if have < size {
            return Err(Violation { vuid: info_vuid("opMode-12314"), message: format!("destination {at:#x} holds {have} bytes; the result takes {size}") });
        }
        if overlaps(at, size, a.scratch, clas::SCRATCH_SIZE) {
            return Err(Violation { vuid: cmd_vuid("dstAddressesArray-10455"), message: format!("destination {at:#x} overlaps scratchData") });
        }
        if let Some(&(o, _)) = taken.iter().find(|&&(o, n)| overlaps(at, size, o, n)) {
            return Err(Violation { vuid: info_vuid("opMode-12315"), message: format!("destination {at:#x} overlaps the destination at {o:#x} of an earlier element") });
        }
        Ok(at)
    }

    fn write_outputs(&self, space: &AddressSpace, view: &DeviceInputs<'_>, elements: Vec<Option<Element>>, a: &Addresses) {
        let (astride, sstride) = (self.dst_addresses.stride, self.dst_sizes.stride);
        let end = a.implicit.saturating_add(self.implicit_extent(space, a.implicit));
        let mut next = a.implicit;
        let mut taken = Vec::new();
        for (i, e) in elements.into_iter().enumerate() {
            let i = i as u64;
            let Some(Element { bytes, size, .. }) = e else { continue };
            if let Some(bytes) = bytes {
                let at = match self.mode {
                    OpMode::ImplicitDestinations => {
                        let at = next.next_multiple_of(self.alignment());
                        if at.saturating_add(size) > end {
                            let message = format!("its result does not fit in dstImplicitData (the elements' results pass {end:#x})");
                            report(Some(i), &Violation { vuid: String::new(), message });
                            continue;
                        }
                        next = at + size;
                        at
                    }
                    _ => match self.explicit_destination(space, view, a, i, size, &taken) {
                        Ok(at) => at,
                        Err(v) => {
                            report(Some(i), &v);
                            continue;
                        }
                    },
                };
                if !write(space, at, &bytes) {
                    continue;
                }
                taken.push((at, size));
                if self.mode == OpMode::ImplicitDestinations && a.dst_addresses != 0 {
                    write(space, a.dst_addresses.wrapping_add(i * astride), &at.to_le_bytes());
                }
            }
            // Sizes are written in every mode (EXPLICIT included: what clients read back).
            if a.dst_sizes != 0 {
                write(space, a.dst_sizes.wrapping_add(i * sstride), &(size.min(u32::MAX as u64) as u32).to_le_bytes());
            }
        }
    }
}

impl Exec for ClusterCommand {
    fn name(&self) -> &'static str {
        CMD
    }
    fn execute(&self, ctx: &ExecContext<'_>) -> Result<(), ExecError> {
        let vuid = cmd_vuid("clusterAccelerationStructure-10443");
        match ctx.device.features.cluster_acceleration_structure {
            Some(true) => {}
            Some(false) => {
                diag::vuid(&vuid, CMD, "the clusterAccelerationStructure feature is not enabled; command skipped");
                return Ok(());
            }
            None => feature_struct_missing(&vuid, CMD),
        }
        // The queue worker is the one thread of its own pool (`threads::run_as_inline_worker`):
        // the records' parallel iterators reach the worker pool only through `run_parallel`.
        let space = ctx.memory();
        crate::threads::run_parallel(false, || self.run(space));
        Ok(())
    }
    fn uses(&self, c: &mut Collector<'_>) {
        for a in [self.dst_implicit_data, self.scratch_data, self.dst_addresses.address, self.dst_sizes.address, self.src_infos.address, self.src_infos_count] {
            c.address(a);
        }
    }
}
