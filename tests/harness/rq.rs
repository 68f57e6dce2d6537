//! Ray queries through the API on Arbor or lavapipe (one loader, validation on): a device with
//! acceleration structures, ray queries and buffer device address; a scene (BLASes of
//! `arbor::accel::Geometry`, instance records) built by every build path the driver offers —
//! device, host, indirect, and compacted and deserialized copies of device builds — and a
//! compute dispatch that traces it through a TLAS descriptor. Every object is owned by the
//! [`RqGpu`] and destroyed with it.
use std::cell::RefCell;
use std::ffi::CString;

use arbor::accel::{Geometry, GeometryData, IndexType, VertexFormat};
use arbor_scene::InstanceRecord;
use ash::vk;

use super::accel::ALL_USAGE;
use super::compute::{use_drivers, validated_instance, Driver};
use super::trace::{after_builds, Pipeline};
use super::{lifecycle, Messages};

const LAVAPIPE_MANIFESTS: &[&str] = &["/usr/share/vulkan/icd.d/lvp_icd.x86_64.json", "/usr/share/vulkan/icd.d/lvp_icd.json"];


/// How a scene's structures are made. Every path but `Device` needs a feature lavapipe lacks
/// (host commands, indirect builds) or is Arbor-only here.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BuildPath {
    /// vkCmdBuildAccelerationStructuresKHR.
    Device,
    /// vkBuildAccelerationStructuresKHR, inputs and scratch in host memory, instances naming
    /// BLAS handles.
    Host,
    /// vkCmdBuildAccelerationStructuresIndirectKHR, range records in a buffer.
    Indirect,
    /// Device builds copied with COMPACT into structures of the compacted size: the BLASes, then
    /// a TLAS built over the compacted BLASes, itself compacted.
    Compacted,
    /// Device builds serialized and deserialized into new structures: the BLASes, then the TLAS,
    /// whose serialized BLAS addresses are rewritten to the deserialized BLASes.
    Deserialized,
}

pub const ALL_PATHS: [BuildPath; 5] = [BuildPath::Device, BuildPath::Host, BuildPath::Indirect, BuildPath::Compacted, BuildPath::Deserialized];

/// A scene: BLASes (their geometries) and instances whose `reference` is the BLAS index + 1
/// (0: inactive).
pub struct Scene<'a> {
    pub blases: Vec<Vec<Geometry<'a>>>,
    pub instances: Vec<InstanceRecord>,
}

/// A buffer with host-visible, coherent memory and a device address.
struct Buffer {
    buffer: vk::Buffer,
    memory: vk::DeviceMemory,
    ptr: *mut u8,
    address: u64,
    size: u64,
}

/// An acceleration structure in a buffer of its own.
#[derive(Clone, Copy, Debug)]
pub struct Structure {
    pub s: vk::AccelerationStructureKHR,
    pub address: u64,
    buffer: usize,
}

/// What `build` made: the TLAS and the BLASes it refers to.
pub struct Built {
    pub tlas: Structure,
    pub blases: Vec<Structure>,
}

/// One device with one queue, validation on.
pub struct RqGpu {
    pub driver: Driver,
    entry: ash::Entry,
    instance: ash::Instance,
    physical: vk::PhysicalDevice,
    pub device: ash::Device,
    queue: vk::Queue,
    pub ext: ash::khr::acceleration_structure::Device,
    pool: vk::CommandPool,
    messages: Messages,
    messenger: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    /// accelerationStructureHostCommands and accelerationStructureIndirectBuild.
    pub host_commands: bool,
    pub indirect_build: bool,
    buffers: RefCell<Vec<Buffer>>,
    structures: RefCell<Vec<vk::AccelerationStructureKHR>>,
}

impl RqGpu {
    pub fn arbor() -> RqGpu {
        RqGpu::new(Driver::Arbor).expect("Arbor's physical device with VK_KHR_ray_query")
    }

    /// lavapipe with ray queries, or None with a printed message saying the comparison is
    /// skipped (not installed, or a Mesa without VK_KHR_ray_query).
    pub fn lavapipe() -> Option<RqGpu> {
        if !LAVAPIPE_MANIFESTS.iter().any(|p| std::path::Path::new(p).exists()) {
            println!("lavapipe is not installed (no lvp_icd manifest): the lavapipe comparison is skipped");
            return None;
        }
        let g = RqGpu::new(Driver::Lavapipe);
        if g.is_none() {
            println!("lavapipe offers no device with VK_KHR_ray_query (Mesa before 25?): the lavapipe comparison is skipped");
        }
        g
    }

    fn find_physical(instance: &ash::Instance, driver: Driver) -> Option<vk::PhysicalDevice> {
        // SAFETY: plain queries.
        unsafe {
            instance.enumerate_physical_devices().unwrap().into_iter().find(|&pd| {
                let p = instance.get_physical_device_properties(pd);
                let name = p.device_name_as_c_str().unwrap().to_str().unwrap().to_string();
                let right = match driver {
                    Driver::Arbor => name == "Arbor (software)",
                    Driver::Lavapipe => name.starts_with("llvmpipe"),
                };
                let exts = instance.enumerate_device_extension_properties(pd).unwrap_or_default();
                let has = |e: &str| exts.iter().any(|x| x.extension_name_as_c_str().unwrap().to_str().unwrap() == e);
                right && has("VK_KHR_ray_query") && has("VK_KHR_acceleration_structure")
            })
        }
    }

    // One function: instance, physical device, feature query and device creation in order.
    fn new(driver: Driver) -> Option<RqGpu> {
        use_drivers();
        let _serial = lifecycle();
        // SAFETY: loading the system Vulkan loader.
        let entry = unsafe { ash::Entry::load() }.expect("libvulkan.so.1");
        let (instance, du, messenger, messages) = validated_instance(&entry);
        // SAFETY: valid create infos; everything is destroyed in Drop.
        unsafe {
            let Some(physical) = RqGpu::find_physical(&instance, driver) else {
                du.destroy_debug_utils_messenger(messenger, None);
                instance.destroy_instance(None);
                return None;
            };
            let mut have = vk::PhysicalDeviceAccelerationStructureFeaturesKHR::default();
            let mut f2 = vk::PhysicalDeviceFeatures2::default().push_next(&mut have);
            instance.get_physical_device_features2(physical, &mut f2);
            let (host_commands, indirect_build) = (have.acceleration_structure_host_commands == vk::TRUE, have.acceleration_structure_indirect_build == vk::TRUE);
            // VK_KHR_acceleration_structure and its dependencies. The extensions' own feature
            // structures, not Vulkan 1.2's: with that one chained, enabling
            // VK_EXT_descriptor_indexing would also require its umbrella feature, which Arbor
            // does not claim.
            let dev_exts: Vec<CString> = ["VK_KHR_acceleration_structure", "VK_KHR_ray_query", "VK_KHR_deferred_host_operations", "VK_KHR_buffer_device_address", "VK_EXT_descriptor_indexing"]
                .iter()
                .map(|e| CString::new(*e).unwrap())
                .collect();
            let ext_p: Vec<*const i8> = dev_exts.iter().map(|c| c.as_ptr()).collect();
            let prio = [1.0f32];
            let qci = [vk::DeviceQueueCreateInfo::default().queue_family_index(0).queue_priorities(&prio)];
            let mut bda = vk::PhysicalDeviceBufferDeviceAddressFeatures::default().buffer_device_address(true);
            let mut asf = vk::PhysicalDeviceAccelerationStructureFeaturesKHR::default()
                .acceleration_structure(true)
                .acceleration_structure_host_commands(host_commands)
                .acceleration_structure_indirect_build(indirect_build);
            let mut rq = vk::PhysicalDeviceRayQueryFeaturesKHR::default().ray_query(true);
            let dci = vk::DeviceCreateInfo::default().queue_create_infos(&qci).enabled_extension_names(&ext_p).push_next(&mut bda).push_next(&mut asf).push_next(&mut rq);
            let device = instance.create_device(physical, &dci, None).expect("vkCreateDevice");
            let queue = device.get_device_queue(0, 0);
            let ext = ash::khr::acceleration_structure::Device::new(&instance, &device);
            let pool = device.create_command_pool(&vk::CommandPoolCreateInfo::default().queue_family_index(0), None).unwrap();
            Some(RqGpu {
                driver,
                entry,
                instance,
                physical,
                device,
                queue,
                ext,
                pool,
                messages,
                messenger: Some((du, messenger)),
                host_commands,
                indirect_build,
                buffers: RefCell::new(Vec::new()),
                structures: RefCell::new(Vec::new()),
            })
        }
    }

    /// Fail if the validation layer said anything.
    pub fn assert_quiet(&self) {
        let m = self.messages.lock().unwrap().clone();
        assert!(m.is_empty(), "validation messages on {:?}:\n{}", self.driver, m.join("\n"));
    }

    fn memory_type(&self, bits: u32) -> u32 {
        let want = vk::MemoryPropertyFlags::HOST_VISIBLE | vk::MemoryPropertyFlags::HOST_COHERENT;
        // SAFETY: plain query.
        let mp = unsafe { self.instance.get_physical_device_memory_properties(self.physical) };
        (0..mp.memory_type_count).find(|&i| bits & (1 << i) != 0 && mp.memory_types[i as usize].property_flags.contains(want)).expect("host-visible memory")
    }

    /// A zeroed buffer of `size` bytes usable in every role these tests need; returns its index.
    fn buffer(&self, size: u64) -> usize {
        let size = size.max(16);
        let d = &self.device;
        // SAFETY: valid create infos; destroyed in Drop.
        let b = unsafe {
            let buffer = d.create_buffer(&vk::BufferCreateInfo::default().size(size).usage(ALL_USAGE | vk::BufferUsageFlags::UNIFORM_BUFFER), None).unwrap();
            let req = d.get_buffer_memory_requirements(buffer);
            let mut flags = vk::MemoryAllocateFlagsInfo::default().flags(vk::MemoryAllocateFlags::DEVICE_ADDRESS);
            let ai = vk::MemoryAllocateInfo::default().allocation_size(req.size).memory_type_index(self.memory_type(req.memory_type_bits)).push_next(&mut flags);
            let memory = d.allocate_memory(&ai, None).unwrap();
            d.bind_buffer_memory(buffer, memory, 0).unwrap();
            let ptr = d.map_memory(memory, 0, vk::WHOLE_SIZE, vk::MemoryMapFlags::empty()).unwrap() as *mut u8;
            std::ptr::write_bytes(ptr, 0, size as usize);
            let address = d.get_buffer_device_address(&vk::BufferDeviceAddressInfo::default().buffer(buffer));
            Buffer { buffer, memory, ptr, address, size }
        };
        let mut all = self.buffers.borrow_mut();
        all.push(b);
        all.len() - 1
    }

    fn upload(&self, data: &[u8]) -> usize {
        let b = self.buffer(data.len() as u64);
        self.write(b, 0, data);
        b
    }

    fn write(&self, b: usize, at: usize, data: &[u8]) {
        let all = self.buffers.borrow();
        assert!(at + data.len() <= all[b].size as usize);
        // SAFETY: mapped memory of the buffer, inside its size (asserted).
        unsafe { std::ptr::copy_nonoverlapping(data.as_ptr(), all[b].ptr.add(at), data.len()) };
    }

    fn read(&self, b: usize, len: usize) -> Vec<u8> {
        let all = self.buffers.borrow();
        assert!(len <= all[b].size as usize);
        // SAFETY: mapped, coherent memory; the queue is idle (every submission is waited for).
        unsafe { std::slice::from_raw_parts(all[b].ptr, len).to_vec() }
    }

    fn address(&self, b: usize) -> u64 {
        self.buffers.borrow()[b].address
    }

    fn vk_buffer(&self, b: usize) -> vk::Buffer {
        self.buffers.borrow()[b].buffer
    }

    /// Record with `f`, submit, wait.
    pub fn submit(&self, f: impl FnOnce(vk::CommandBuffer)) {
        let d = &self.device;
        // SAFETY: valid pool; the command buffer and fence are freed after the wait.
        unsafe {
            let cb = d.allocate_command_buffers(&vk::CommandBufferAllocateInfo::default().command_pool(self.pool).command_buffer_count(1)).unwrap()[0];
            d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default().flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT)).unwrap();
            f(cb);
            d.end_command_buffer(cb).unwrap();
            let fence = d.create_fence(&vk::FenceCreateInfo::default(), None).unwrap();
            let cbs = [cb];
            d.queue_submit(self.queue, &[vk::SubmitInfo::default().command_buffers(&cbs)], fence).unwrap();
            d.wait_for_fences(&[fence], true, 120_000_000_000).expect("the submission finishes");
            d.destroy_fence(fence, None);
            d.free_command_buffers(self.pool, &cbs);
        }
    }

    /// A structure of `size` bytes at offset 0 of a buffer of its own.
    fn structure(&self, ty: vk::AccelerationStructureTypeKHR, size: u64) -> Structure {
        let buffer = self.buffer(size);
        let info = vk::AccelerationStructureCreateInfoKHR::default().buffer(self.vk_buffer(buffer)).size(size).ty(ty);
        // SAFETY: valid create info; destroyed in Drop.
        let s = unsafe { self.ext.create_acceleration_structure(&info, None) }.unwrap();
        self.structures.borrow_mut().push(s);
        // SAFETY: a live structure.
        let address = unsafe { self.ext.get_acceleration_structure_device_address(&vk::AccelerationStructureDeviceAddressInfoKHR::default().acceleration_structure(s)) };
        Structure { s, address, buffer }
    }
}

impl RqGpu {
    /// Destroy everything, then fail if the validation layer said anything (destruction
    /// included).
    pub fn finish(mut self) {
        self.teardown();
        self.assert_quiet();
    }

    fn teardown(&mut self) {
        if let Some((du, m)) = self.messenger.take() {
            let _serial = lifecycle();
            // SAFETY: every submission was waited for; each object is destroyed once.
            unsafe {
                let _ = self.device.device_wait_idle();
                for s in self.structures.borrow().iter() {
                    self.ext.destroy_acceleration_structure(*s, None);
                }
                for b in self.buffers.borrow().iter() {
                    self.device.destroy_buffer(b.buffer, None);
                    self.device.free_memory(b.memory, None);
                }
                self.device.destroy_command_pool(self.pool, None);
                self.device.destroy_device(None);
                du.destroy_debug_utils_messenger(m, None);
                self.instance.destroy_instance(None);
            }
        }
    }
}

impl Drop for RqGpu {
    fn drop(&mut self) {
        self.teardown();
    }
}

// ---------------------------------------------------------------------------------------------
// Builds

/// Bytes copied into 16-byte aligned host memory (host builds read vertices, indices, boxes,
/// transforms and instances at their natural alignment).
struct HostBytes(Vec<u128>);

impl HostBytes {
    fn new(b: &[u8]) -> HostBytes {
        let mut v = vec![0u128; b.len().div_ceil(16).max(1)];
        bytemuck::cast_slice_mut::<u128, u8>(&mut v)[..b.len()].copy_from_slice(b);
        HostBytes(v)
    }
    fn address(&self) -> u64 {
        self.0.as_ptr() as u64
    }
}

fn vk_format(f: VertexFormat) -> vk::Format {
    match f {
        VertexFormat::R32G32B32Sfloat => vk::Format::R32G32B32_SFLOAT,
        other => panic!("rq harness: vertex format {other:?} not mapped"),
    }
}

fn vk_index(t: IndexType) -> vk::IndexType {
    match t {
        IndexType::U32 => vk::IndexType::UINT32,
        IndexType::U16 => vk::IndexType::UINT16,
        IndexType::None => vk::IndexType::NONE_KHR,
    }
}

/// Where the input bytes of one geometry are: device addresses or host pointers.
struct Placed {
    data: u64,
    indices: u64,
    transform: u64,
}

type VkGeom = vk::AccelerationStructureGeometryKHR<'static>;

fn vk_geometry(g: &Geometry, p: &Placed) -> VkGeom {
    let flags = vk::GeometryFlagsKHR::from_raw(g.flags.0);
    let c = |a: u64| vk::DeviceOrHostAddressConstKHR { device_address: a };
    let geometry = match g.data {
        GeometryData::Triangles { format, stride, max_vertex, index_type, .. } => vk::AccelerationStructureGeometryDataKHR {
            triangles: vk::AccelerationStructureGeometryTrianglesDataKHR::default()
                .vertex_format(vk_format(format))
                .vertex_data(c(p.data))
                .vertex_stride(stride)
                .max_vertex(max_vertex)
                .index_type(vk_index(index_type))
                .index_data(c(p.indices))
                .transform_data(c(p.transform)),
        },
        GeometryData::Aabbs { stride, .. } => vk::AccelerationStructureGeometryDataKHR { aabbs: vk::AccelerationStructureGeometryAabbsDataKHR::default().data(c(p.data)).stride(stride) },
        GeometryData::Instances { .. } => panic!("rq harness: instances are the scene's, not a BLAS geometry"),
    };
    let ty = if matches!(g.data, GeometryData::Triangles { .. }) { vk::GeometryTypeKHR::TRIANGLES } else { vk::GeometryTypeKHR::AABBS };
    VkGeom::default().geometry_type(ty).flags(flags).geometry(geometry)
}

fn transform_bytes(t: &[f32; 12]) -> Vec<u8> {
    t.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// The input bytes of a geometry: (vertices or boxes, indices, transform).
fn input_bytes<'a>(g: &Geometry<'a>) -> (&'a [u8], &'a [u8], Option<Vec<u8>>) {
    match g.data {
        GeometryData::Triangles { vertices, indices, transform, .. } => (vertices, indices, transform.as_ref().map(transform_bytes)),
        GeometryData::Aabbs { data, .. } => (data, &[], None),
        GeometryData::Instances { .. } => panic!("rq harness: instances are not a BLAS geometry"),
    }
}

const FLAGS: vk::BuildAccelerationStructureFlagsKHR =
    vk::BuildAccelerationStructureFlagsKHR::from_raw(vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE.as_raw() | vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION.as_raw());

fn build_info<'a>(ty: vk::AccelerationStructureTypeKHR, geoms: &'a [VkGeom]) -> vk::AccelerationStructureBuildGeometryInfoKHR<'a> {
    vk::AccelerationStructureBuildGeometryInfoKHR::default().ty(ty).flags(FLAGS).mode(vk::BuildAccelerationStructureModeKHR::BUILD).geometries(geoms)
}

fn instances_geometry(address: u64) -> VkGeom {
    VkGeom::default().geometry_type(vk::GeometryTypeKHR::INSTANCES).geometry(vk::AccelerationStructureGeometryDataKHR {
        instances: vk::AccelerationStructureGeometryInstancesDataKHR::default().data(vk::DeviceOrHostAddressConstKHR { device_address: address }),
    })
}

impl RqGpu {
    /// Builds `scene` by `path`.
    pub fn build(&self, scene: &Scene, path: BuildPath) -> Built {
        match path {
            BuildPath::Device | BuildPath::Indirect => {
                let blases: Vec<Structure> = scene.blases.iter().map(|g| self.device_build(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL, g, &[], path)).collect();
                let tlas = self.device_tlas(scene, &blases, path);
                Built { tlas, blases }
            }
            BuildPath::Host => self.host_build(scene),
            BuildPath::Compacted => {
                let blases: Vec<Structure> = scene.blases.iter().map(|g| self.device_build(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL, g, &[], BuildPath::Device)).collect();
                let blases: Vec<Structure> = blases.iter().map(|b| self.compact(*b, vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL)).collect();
                let tlas = self.device_tlas(scene, &blases, BuildPath::Device);
                Built { tlas: self.compact(tlas, vk::AccelerationStructureTypeKHR::TOP_LEVEL), blases }
            }
            BuildPath::Deserialized => {
                let built = self.build(scene, BuildPath::Device);
                let mut moved = Vec::new();
                for b in &built.blases {
                    let blob = self.serialize(*b);
                    moved.push(self.deserialize(&blob, vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL));
                }
                let mut blob = self.serialize(built.tlas);
                // The serialized TLAS lists the BLAS address of each active instance after its
                // 56-byte header: point them at the deserialized BLASes.
                let n = u64::from_le_bytes(blob[48..56].try_into().unwrap()) as usize;
                for k in 0..n {
                    let at = 56 + 8 * k;
                    let old = u64::from_le_bytes(blob[at..at + 8].try_into().unwrap());
                    let i = built.blases.iter().position(|b| b.address == old).expect("a serialized BLAS address is one of the scene's");
                    blob[at..at + 8].copy_from_slice(&moved[i].address.to_le_bytes());
                }
                Built { tlas: self.deserialize(&blob, vk::AccelerationStructureTypeKHR::TOP_LEVEL), blases: moved }
            }
        }
    }

    fn device_tlas(&self, scene: &Scene, blases: &[Structure], path: BuildPath) -> Structure {
        let records: Vec<InstanceRecord> = scene
            .instances
            .iter()
            .map(|r| InstanceRecord { reference: if r.reference == 0 { 0 } else { blases[r.reference as usize - 1].address }, ..*r })
            .collect();
        let bytes = InstanceRecord::pack(&records);
        let g = [Geometry { flags: arbor::accel::GeometryFlags(0), primitive_count: records.len() as u32, data: GeometryData::Instances { array_of_pointers: false, data: &bytes } }];
        self.device_build(vk::AccelerationStructureTypeKHR::TOP_LEVEL, &g, &bytes, path)
    }

    /// One structure built with vkCmdBuildAccelerationStructuresKHR (or its indirect form).
    /// For a TLAS, `geoms` is one instances geometry and `instances` its packed records.
    fn device_build(&self, ty: vk::AccelerationStructureTypeKHR, geoms: &[Geometry], instances: &[u8], path: BuildPath) -> Structure {
        let vk_geoms: Vec<VkGeom> = if ty == vk::AccelerationStructureTypeKHR::TOP_LEVEL {
            vec![instances_geometry(self.address(self.upload(instances)))]
        } else {
            geoms
                .iter()
                .map(|g| {
                    let (data, indices, transform) = input_bytes(g);
                    let placed = Placed {
                        data: self.address(self.upload(data)),
                        indices: if indices.is_empty() { 0 } else { self.address(self.upload(indices)) },
                        transform: transform.map_or(0, |t| self.address(self.upload(&t))),
                    };
                    vk_geometry(g, &placed)
                })
                .collect()
        };
        let counts: Vec<u32> = geoms.iter().map(|g| g.primitive_count).collect();
        let info = build_info(ty, &vk_geoms);
        let sizes = self.sizes(vk::AccelerationStructureBuildTypeKHR::DEVICE, &info, &counts);
        let dst = self.structure(ty, sizes.acceleration_structure_size);
        let scratch = self.buffer(sizes.build_scratch_size);
        let info = info.dst_acceleration_structure(dst.s).scratch_data(vk::DeviceOrHostAddressKHR { device_address: self.address(scratch) });
        let ranges: Vec<vk::AccelerationStructureBuildRangeInfoKHR> = counts.iter().map(|&c| vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(c)).collect();
        if path == BuildPath::Indirect {
            let records: Vec<u8> = counts.iter().flat_map(|&c| [c, 0, 0, 0]).flat_map(u32::to_le_bytes).collect();
            let at = self.address(self.upload(&records));
            // SAFETY: recording command buffer; one info with its record array and counts.
            self.submit(|cb| unsafe { self.ext.cmd_build_acceleration_structures_indirect(cb, &[info], &[at], &[16], &[&counts]) });
        } else {
            // SAFETY: recording command buffer; one info with its ranges.
            self.submit(|cb| unsafe { self.ext.cmd_build_acceleration_structures(cb, &[info], &[&ranges]) });
        }
        dst
    }

    fn sizes(&self, ty: vk::AccelerationStructureBuildTypeKHR, info: &vk::AccelerationStructureBuildGeometryInfoKHR, counts: &[u32]) -> vk::AccelerationStructureBuildSizesInfoKHR<'static> {
        let mut s = vk::AccelerationStructureBuildSizesInfoKHR::default();
        // SAFETY: valid info; one count per geometry.
        unsafe { self.ext.get_acceleration_structure_build_sizes(ty, info, counts, &mut s) };
        s
    }

    /// Every structure built with vkBuildAccelerationStructuresKHR from host memory.
    fn host_build(&self, scene: &Scene) -> Built {
        assert!(self.host_commands, "{:?} has no host commands", self.driver);
        let mut blases = Vec::new();
        for geoms in &scene.blases {
            let held: Vec<(HostBytes, HostBytes, Option<HostBytes>)> = geoms
                .iter()
                .map(|g| {
                    let (data, indices, transform) = input_bytes(g);
                    (HostBytes::new(data), HostBytes::new(indices), transform.map(|t| HostBytes::new(&t)))
                })
                .collect();
            let vk_geoms: Vec<VkGeom> = geoms
                .iter()
                .zip(&held)
                .map(|(g, (d, i, t))| {
                    let indices = if input_bytes(g).1.is_empty() { 0 } else { i.address() };
                    vk_geometry(g, &Placed { data: d.address(), indices, transform: t.as_ref().map_or(0, |t| t.address()) })
                })
                .collect();
            let counts: Vec<u32> = geoms.iter().map(|g| g.primitive_count).collect();
            blases.push(self.host_build_one(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL, &vk_geoms, &counts));
        }
        let records: Vec<InstanceRecord> = scene
            .instances
            .iter()
            .map(|r| InstanceRecord { reference: if r.reference == 0 { 0 } else { vk::Handle::as_raw(blases[r.reference as usize - 1].s) }, ..*r })
            .collect();
        let held = HostBytes::new(&InstanceRecord::pack(&records));
        let tlas = self.host_build_one(vk::AccelerationStructureTypeKHR::TOP_LEVEL, &[instances_geometry(held.address())], &[records.len() as u32]);
        Built { tlas, blases }
    }

    fn host_build_one(&self, ty: vk::AccelerationStructureTypeKHR, geoms: &[VkGeom], counts: &[u32]) -> Structure {
        let info = build_info(ty, geoms);
        let sizes = self.sizes(vk::AccelerationStructureBuildTypeKHR::HOST, &info, counts);
        let dst = self.structure(ty, sizes.acceleration_structure_size);
        let mut scratch = vec![0u128; (sizes.build_scratch_size as usize).div_ceil(16).max(1)];
        let info = info.dst_acceleration_structure(dst.s).scratch_data(vk::DeviceOrHostAddressKHR { host_address: scratch.as_mut_ptr().cast() });
        let ranges: Vec<vk::AccelerationStructureBuildRangeInfoKHR> = counts.iter().map(|&c| vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(c)).collect();
        // SAFETY: the inputs (held by the caller) and scratch outlive this call, which builds
        // without a deferred operation.
        unsafe { self.ext.build_acceleration_structures(vk::DeferredOperationKHR::null(), &[info], &[&ranges]) }.expect("vkBuildAccelerationStructuresKHR");
        dst
    }

    /// One property through a query pool.
    fn property(&self, s: Structure, ty: vk::QueryType) -> u64 {
        let d = &self.device;
        // SAFETY: valid create info; destroyed below.
        let pool = unsafe { d.create_query_pool(&vk::QueryPoolCreateInfo::default().query_type(ty).query_count(1), None) }.unwrap();
        self.submit(|cb| {
            // SAFETY: recording command buffer; live pool and structure.
            unsafe {
                d.cmd_reset_query_pool(cb, pool, 0, 1);
                self.ext.cmd_write_acceleration_structures_properties(cb, &[s.s], ty, pool, 0);
            }
        });
        let mut out = [0u64; 1];
        // SAFETY: the pool's one query was written by the submission above.
        unsafe {
            d.get_query_pool_results(pool, 0, &mut out, vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT).unwrap();
            d.destroy_query_pool(pool, None);
        }
        out[0]
    }

    fn compact(&self, src: Structure, ty: vk::AccelerationStructureTypeKHR) -> Structure {
        let size = self.property(src, vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR);
        let dst = self.structure(ty, size);
        let info = vk::CopyAccelerationStructureInfoKHR::default().src(src.s).dst(dst.s).mode(vk::CopyAccelerationStructureModeKHR::COMPACT);
        // SAFETY: recording command buffer; live structures.
        self.submit(|cb| unsafe { self.ext.cmd_copy_acceleration_structure(cb, &info) });
        dst
    }

    fn serialize(&self, src: Structure) -> Vec<u8> {
        let size = self.property(src, vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_SIZE_KHR);
        let b = self.buffer(size);
        let info = vk::CopyAccelerationStructureToMemoryInfoKHR::default()
            .src(src.s)
            .dst(vk::DeviceOrHostAddressKHR { device_address: self.address(b) })
            .mode(vk::CopyAccelerationStructureModeKHR::SERIALIZE);
        // SAFETY: recording command buffer; a live structure and a buffer of the queried size.
        self.submit(|cb| unsafe { self.ext.cmd_copy_acceleration_structure_to_memory(cb, &info) });
        self.read(b, size as usize)
    }

    fn deserialize(&self, blob: &[u8], ty: vk::AccelerationStructureTypeKHR) -> Structure {
        // The serialized header says how large the structure is once deserialized.
        let size = u64::from_le_bytes(blob[40..48].try_into().unwrap());
        let dst = self.structure(ty, size);
        let src = self.upload(blob);
        let info = vk::CopyMemoryToAccelerationStructureInfoKHR::default()
            .src(vk::DeviceOrHostAddressConstKHR { device_address: self.address(src) })
            .dst(dst.s)
            .mode(vk::CopyAccelerationStructureModeKHR::DESERIALIZE);
        // SAFETY: recording command buffer; serialized bytes in a live buffer.
        self.submit(|cb| unsafe { self.ext.cmd_copy_memory_to_acceleration_structure(cb, &info) });
        dst
    }
}

// ---------------------------------------------------------------------------------------------
// Tracing

impl RqGpu {
    /// One dispatch of `spirv` (entry `main`): the TLAS at set 0 binding 0, `buffers` as
    /// storage buffers at bindings 1, 2, …, `push` as push constants, `groups` workgroups in x.
    /// Returns every buffer's bytes afterwards.
    pub fn trace(&self, spirv: &[u32], tlas: &Structure, buffers: &[Vec<u8>], push: &[u8], groups: u32) -> Vec<Vec<u8>> {
        let d = &self.device;
        let stage = vk::ShaderStageFlags::COMPUTE;
        let ids: Vec<usize> = buffers.iter().map(|b| self.upload(b)).collect();
        let mut bindings = vec![vk::DescriptorSetLayoutBinding::default().binding(0).descriptor_type(vk::DescriptorType::ACCELERATION_STRUCTURE_KHR).descriptor_count(1).stage_flags(stage)];
        for k in 0..buffers.len() {
            bindings.push(vk::DescriptorSetLayoutBinding::default().binding(k as u32 + 1).descriptor_type(vk::DescriptorType::STORAGE_BUFFER).descriptor_count(1).stage_flags(stage));
        }
        // SAFETY: valid create infos; everything is destroyed before returning, after the wait.
        unsafe {
            let set_layout = d.create_descriptor_set_layout(&vk::DescriptorSetLayoutCreateInfo::default().bindings(&bindings), None).unwrap();
            let sizes = [
                vk::DescriptorPoolSize { ty: vk::DescriptorType::ACCELERATION_STRUCTURE_KHR, descriptor_count: 1 },
                vk::DescriptorPoolSize { ty: vk::DescriptorType::STORAGE_BUFFER, descriptor_count: buffers.len().max(1) as u32 },
            ];
            let pool = d.create_descriptor_pool(&vk::DescriptorPoolCreateInfo::default().max_sets(1).pool_sizes(&sizes), None).unwrap();
            let layouts = [set_layout];
            let set = d.allocate_descriptor_sets(&vk::DescriptorSetAllocateInfo::default().descriptor_pool(pool).set_layouts(&layouts)).unwrap()[0];
            let structures = [tlas.s];
            let mut as_info = vk::WriteDescriptorSetAccelerationStructureKHR::default().acceleration_structures(&structures);
            let infos: Vec<[vk::DescriptorBufferInfo; 1]> = ids.iter().map(|&b| [vk::DescriptorBufferInfo { buffer: self.vk_buffer(b), offset: 0, range: vk::WHOLE_SIZE }]).collect();
            let mut writes = vec![vk::WriteDescriptorSet::default()
                .dst_set(set)
                .dst_binding(0)
                .descriptor_count(1)
                .descriptor_type(vk::DescriptorType::ACCELERATION_STRUCTURE_KHR)
                .push_next(&mut as_info)];
            for (k, info) in infos.iter().enumerate() {
                writes.push(vk::WriteDescriptorSet::default().dst_set(set).dst_binding(k as u32 + 1).descriptor_type(vk::DescriptorType::STORAGE_BUFFER).buffer_info(info));
            }
            d.update_descriptor_sets(&writes, &[]);
            let push_size = (push.len() as u32).next_multiple_of(4);
            let pipeline = Pipeline::new(d, spirv, set_layout, push_size);
            let mut push = push.to_vec();
            push.resize(push_size as usize, 0);
            self.submit(|cb| {
                after_builds(d, cb);
                pipeline.record(d, cb, set, &push, groups);
            });
            pipeline.destroy(d);
            d.destroy_descriptor_pool(pool, None);
            d.destroy_descriptor_set_layout(set_layout, None);
        }
        ids.iter().zip(buffers).map(|(&b, data)| self.read(b, data.len())).collect()
    }
}
