//! vkCmdBuildClusterAccelerationStructureIndirectNV as the runtime runs it: the recorded
//! [`ClusterCommand`] resolves its address indirections, reads the element count and the argument
//! records from device memory when the queue executes it, makes every result in host memory
//! (`accel::clas`), then writes results, addresses and sizes by mode. Making every result before
//! writing any is what lets a move's destinations overlap other moves' sources.
//!
//! Owns the execution model of nv-extensions.md B.6; the blob formats are `accel::clas`'s. A
//! failing element is reported and skipped; the others complete.
use rayon::prelude::*;

use super::inputs::DeviceInputs;
use crate::accel::clas::args::{AddressInfo, BuildClustersBottomLevelInfo, BuildTriangleClusterInfo, BuildTriangleClusterTemplateInfo, InstantiateClusterInfo, ObjectType, OpMode, OpType};
use crate::accel::clas::{self, ClusterError, Kind};
use crate::accel::{DeviceView, VertexFormat};
use crate::diag;
use crate::memory::region::Region;
use crate::memory::AddressSpace;
use crate::runtime::command::{Exec, ExecContext, ExecError};
use crate::runtime::in_use::Collector;

const CMD: &str = "vkCmdBuildClusterAccelerationStructureIndirectNV";

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

/// What one element produces: its result bytes (None in COMPUTE_SIZES mode) and its size.
type Produced = Result<(Option<Vec<u8>>, u64), ClusterError>;

impl ClusterCommand {
    /// A field after its INDIRECTED bit: the address read there, or the field itself.
    fn resolve(&self, view: &DeviceInputs<'_>, bit: u32, field: u64) -> Option<u64> {
        if self.address_resolution & bit == 0 || field == 0 {
            return Some(field);
        }
        let a = read_u64(view, field);
        if a.is_none() {
            diag::report(diag::Level::Error, CMD, &format!("the indirected address at {field:#x} is unreadable"));
        }
        a
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

    /// Element `i`'s argument record.
    fn record<'v>(&self, view: &'v DeviceInputs<'_>, src: u64, i: u64) -> Result<&'v [u8], ClusterError> {
        let size = self.op.record_size();
        let stride = if self.src_infos.stride == 0 { size } else { self.src_infos.stride };
        let address = src.wrapping_add(i * stride);
        view.bytes(address, size).ok_or(ClusterError::Unreadable { what: "srcInfosArray element", address })
    }

    // One function: one arm per op type, each reading its record, sizing and building.
    fn produce(&self, view: &DeviceInputs<'_>, rec: &[u8]) -> Produced {
        let sizes_only = self.mode == OpMode::ComputeSizes;
        let format = || self.vertex_format.ok_or(ClusterError::NotA("supported vertex format"));
        let structure = |address: u64| view.acceleration_structure(address).ok_or(ClusterError::Unreadable { what: "cluster object", address });
        let alloc = |n: u64| vec![0u8; n as usize];
        match self.op {
            OpType::BuildTriangleCluster => {
                let a: BuildTriangleClusterInfo = bytemuck::pod_read_unaligned(rec);
                let size = clas::clas_size(a.triangle_count() as u64);
                if sizes_only {
                    return Ok((None, size));
                }
                let mut dst = alloc(size);
                clas::build_clas(&a, format()?, view, &mut dst)?;
                Ok((Some(dst), size))
            }
            OpType::BuildTriangleClusterTemplate => {
                let a: BuildTriangleClusterTemplateInfo = bytemuck::pod_read_unaligned(rec);
                let size = clas::template_size(a.cluster.triangle_count() as u64, a.cluster.vertex_buffer != 0);
                if sizes_only {
                    return Ok((None, size));
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
                Ok((Some(dst), size))
            }
            OpType::InstantiateTriangleCluster => {
                let a: InstantiateClusterInfo = bytemuck::pod_read_unaligned(rec);
                let tpl = structure(a.cluster_template_address)?;
                let t = clas::open(tpl).filter(|b| b.kind == Kind::Template).ok_or(ClusterError::NotA("cluster template"))?.header.triangle_count;
                // A CLAS's size depends on its triangle count only: exact even without vertices.
                let size = clas::clas_size(t as u64);
                if sizes_only {
                    return Ok((None, size));
                }
                let mut dst = alloc(size);
                clas::instantiate(tpl, &a, view, &mut dst)?;
                Ok((Some(dst), size))
            }
            OpType::BuildClustersBottomLevel => {
                let a: BuildClustersBottomLevelInfo = bytemuck::pod_read_unaligned(rec);
                let stride = if a.cluster_references_stride == 0 { 8 } else { a.cluster_references_stride as u64 };
                let mut clusters = Vec::with_capacity(a.cluster_references_count as usize);
                for k in 0..a.cluster_references_count as u64 {
                    let at = a.cluster_references.wrapping_add(k * stride);
                    let address = read_u64(view, at).ok_or(ClusterError::Unreadable { what: "cluster reference", address: at })?;
                    clusters.push((address, structure(address).map_err(|_| ClusterError::NotAClas { address })?));
                }
                let triangles: u64 = clusters.iter().map(|c| clas::open(c.1).map_or(0, |b| b.header.triangle_count as u64)).sum();
                let bound = clas::blas_size_for(clusters.len() as u64, triangles);
                if sizes_only {
                    return Ok((None, bound));
                }
                let mut dst = alloc(bound);
                let used = clas::build_cluster_blas(&clusters, self.build_flags, &mut dst)?;
                dst.truncate(used as usize);
                Ok((Some(dst), used))
            }
            OpType::MoveObjects => {
                let a: AddressInfo = bytemuck::pod_read_unaligned(rec);
                let bytes = structure(a.address)?;
                let (kind, size) = clas::object_size(bytes).ok_or(ClusterError::NotA("cluster object"))?;
                let want = match self.move_type {
                    ObjectType::ClustersBottomLevel => Kind::ClusterBlas,
                    ObjectType::TriangleCluster => Kind::Clas,
                    ObjectType::TriangleClusterTemplate => Kind::Template,
                };
                if kind != want {
                    return Err(ClusterError::NotA("cluster object of the moved type"));
                }
                Ok(((!sizes_only).then(|| bytes[..size as usize].to_vec()), size))
            }
            OpType::GetClusterTemplateIndices => {
                let a: AddressInfo = bytemuck::pod_read_unaligned(rec);
                let tpl = structure(a.address)?;
                let size = clas::template_indices_size(tpl)?;
                if sizes_only {
                    return Ok((None, size));
                }
                let mut dst = alloc(size);
                clas::template_indices(tpl, &mut dst)?;
                Ok((Some(dst), size))
            }
        }
    }

    fn run(&self, space: &AddressSpace) {
        let view = DeviceInputs::new(space, CMD);
        let r = |bit, field| self.resolve(&view, bit, field);
        let (Some(src), Some(count_at), Some(dst_addresses), Some(dst_sizes), Some(implicit)) = (
            r(resolution::SRC_INFOS_ARRAY, self.src_infos.address),
            r(resolution::SRC_INFOS_COUNT, self.src_infos_count),
            r(resolution::DST_ADDRESS_ARRAY, self.dst_addresses.address),
            r(resolution::DST_SIZES_ARRAY, self.dst_sizes.address),
            r(resolution::DST_IMPLICIT_DATA, self.dst_implicit_data),
        ) else {
            return;
        };
        if let Some(scratch) = r(resolution::SCRATCH_DATA, self.scratch_data) {
            self.check_scratch(space, scratch);
        }
        let count = match count_at {
            0 => self.max_count,
            at => match view.bytes(at, 4) {
                Some(b) => u32::from_le_bytes(b.try_into().unwrap_or([0; 4])).min(self.max_count),
                None => {
                    diag::report(diag::Level::Error, CMD, &format!("srcInfosCount {at:#x} is unreadable"));
                    return;
                }
            },
        };
        let produced: Vec<Produced> = (0..count as u64).into_par_iter().map(|i| self.record(&view, src, i).and_then(|rec| self.produce(&view, rec))).collect();
        self.write_outputs(space, &view, produced, dst_addresses, dst_sizes, implicit);
    }

    /// The scratch rules (10446, 10447). Arbor's working arrays live in host memory, so a
    /// violation is reported and the command still runs.
    fn check_scratch(&self, space: &AddressSpace, scratch: u64) {
        if !scratch.is_multiple_of(clas::SCRATCH_ALIGNMENT) {
            diag::vuid(
                "VUID-vkCmdBuildClusterAccelerationStructureIndirectNV-scratchData-10447",
                CMD,
                &format!("scratchData {scratch:#x} is not a multiple of clusterScratchByteAlignment ({})", clas::SCRATCH_ALIGNMENT),
            );
        }
        if let Err(e) = Region::of_device(space, scratch, clas::SCRATCH_SIZE) {
            diag::vuid(
                "VUID-vkCmdBuildClusterAccelerationStructureIndirectNV-scratchData-10446",
                CMD,
                &format!("scratchData {scratch:#x} does not hold the queried scratch size ({} bytes): {e}", clas::SCRATCH_SIZE),
            );
        }
    }

    fn write_outputs(&self, space: &AddressSpace, view: &DeviceInputs<'_>, produced: Vec<Produced>, dst_addresses: u64, dst_sizes: u64, implicit: u64) {
        let astride = if self.dst_addresses.stride == 0 { 8 } else { self.dst_addresses.stride };
        let sstride = if self.dst_sizes.stride == 0 { 4 } else { self.dst_sizes.stride };
        let mut next = implicit;
        for (i, p) in produced.into_iter().enumerate() {
            let i = i as u64;
            let (bytes, size) = match p {
                Ok(v) => v,
                Err(e) => {
                    diag::report(diag::Level::Error, CMD, &format!("element {i}: {e}; nothing written for it"));
                    continue;
                }
            };
            if let Some(bytes) = bytes {
                let at = match self.mode {
                    OpMode::ImplicitDestinations => {
                        let at = next.next_multiple_of(self.alignment());
                        next = at + size;
                        at
                    }
                    _ => match read_u64(view, dst_addresses.wrapping_add(i * astride)) {
                        Some(a) => a,
                        None => {
                            diag::report(diag::Level::Error, CMD, &format!("element {i}: its dstAddressesArray entry is unreadable"));
                            continue;
                        }
                    },
                };
                if !write(space, at, &bytes) {
                    continue;
                }
                if self.mode == OpMode::ImplicitDestinations && dst_addresses != 0 {
                    write(space, dst_addresses.wrapping_add(i * astride), &at.to_le_bytes());
                }
            }
            // Sizes are written in every mode (EXPLICIT included: what clients read back).
            if dst_sizes != 0 {
                write(space, dst_sizes.wrapping_add(i * sstride), &(size.min(u32::MAX as u64) as u32).to_le_bytes());
            }
        }
    }
}

impl Exec for ClusterCommand {
    fn name(&self) -> &'static str {
        CMD
    }
    fn execute(&self, ctx: &ExecContext<'_>) -> Result<(), ExecError> {
        self.run(ctx.memory());
        Ok(())
    }
    fn uses(&self, c: &mut Collector<'_>) {
        for a in [self.dst_implicit_data, self.scratch_data, self.dst_addresses.address, self.dst_sizes.address, self.src_infos.address, self.src_infos_count] {
            c.address(a);
        }
    }
}
