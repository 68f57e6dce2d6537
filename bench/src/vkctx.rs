//! One Vulkan device of one driver: queue, command pool, extension loaders, buffers with device
//! addresses (device-local where the driver has such memory, uploaded through a staging buffer
//! when it is not host-visible), one-shot and repeated timed submissions.
use std::cell::RefCell;
use std::ffi::CStr;
use std::time::Instant;

use ash::vk;

/// VkPhysicalDevicePartitionedAccelerationStructureFeaturesNV (ash 0.38 lacks it), chained by hand.
#[repr(C)]
struct PtlasFeatures {
    s_type: vk::StructureType,
    p_next: *const std::ffi::c_void,
    partitioned_acceleration_structure: vk::Bool32,
}

pub const PTLAS_EXTENSION: &str = "VK_NV_partitioned_acceleration_structure";

/// What a driver offers for the acceleration-structure work.
#[derive(Clone, Debug, Default)]
pub struct Caps {
    pub acceleration_structure: bool,
    pub host_commands: bool,
    pub indirect_build: bool,
    pub deferred: bool,
    pub timestamps: bool,
    pub timestamp_mask: u64,
    pub timestamp_period_ns: f64,
    pub max_primitive_count: u64,
    pub max_instance_count: u64,
    /// VK_KHR_ray_query with its rayQuery feature (the trace workloads).
    pub ray_query: bool,
    /// VK_NV_partitioned_acceleration_structure (the ptlas workloads).
    pub ptlas: bool,
    /// Why the AS work cannot run at all (extension or feature missing).
    pub missing: Option<String>,
}

pub struct Gpu {
    pub device: ash::Device,
    pub name: String,
    pub driver_version: String,
    pub label: String,
    pub queue: vk::Queue,
    pub pool: vk::CommandPool,
    pub caps: Caps,
    pub ext: ash::khr::acceleration_structure::Device,
    pub deferred: ash::khr::deferred_host_operations::Device,
    pub bda: ash::khr::buffer_device_address::Device,
    /// vkGetDeviceProcAddr, for extension commands ash does not wrap (the NV cluster and partitioned ones).
    pub get_device_proc_addr: vk::PFN_vkGetDeviceProcAddr,
    mem: vk::PhysicalDeviceMemoryProperties,
}

/// A buffer with its memory and device address; `ptr` is set when the memory is host-visible.
#[derive(Clone, Copy, Debug)]
pub struct Buf {
    pub buffer: vk::Buffer,
    pub memory: vk::DeviceMemory,
    pub ptr: *mut u8,
    pub address: u64,
    pub size: u64,
}

impl Buf {
    pub fn read(&self, offset: usize, len: usize) -> Vec<u8> {
        assert!(!self.ptr.is_null() && offset + len <= self.size as usize);
        // SAFETY: mapped host-visible memory of `size` bytes.
        unsafe { std::slice::from_raw_parts(self.ptr.add(offset), len).to_vec() }
    }
}

pub const ALL_USAGE: vk::BufferUsageFlags = vk::BufferUsageFlags::from_raw(
    vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS.as_raw()
        | vk::BufferUsageFlags::STORAGE_BUFFER.as_raw()
        | vk::BufferUsageFlags::TRANSFER_SRC.as_raw()
        | vk::BufferUsageFlags::TRANSFER_DST.as_raw()
        | vk::BufferUsageFlags::INDIRECT_BUFFER.as_raw()
        | vk::BufferUsageFlags::ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_KHR.as_raw()
        | vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR.as_raw(),
);

/// Where a buffer lives.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Place {
    /// Device-local memory (host-visible too where the driver has such memory).
    Device,
    /// Host-visible memory (read-backs, host commands).
    Host,
}

fn vk_err(what: &str) -> impl Fn(vk::Result) -> String + '_ {
    move |e| format!("{what}: {e}")
}

impl Gpu {
    /// Create a device with the acceleration-structure extensions and every optional feature the
    /// driver has. `label` names the driver in the report.
    pub fn new(instance: &ash::Instance, physical: vk::PhysicalDevice, label: String) -> Result<Gpu, String> {
        // SAFETY: plain query on a live instance and physical device.
        let props = unsafe { instance.get_physical_device_properties(physical) };
        // SAFETY: NUL-terminated by the driver.
        let name = unsafe { CStr::from_ptr(props.device_name.as_ptr()) }.to_string_lossy().into_owned();
        let driver_version = driver_version(instance, physical, &props);
        // SAFETY: plain query.
        let exts: Vec<String> = unsafe { instance.enumerate_device_extension_properties(physical) }
            .map_err(vk_err("vkEnumerateDeviceExtensionProperties"))?
            .iter()
            // SAFETY: NUL-terminated by the driver.
            .map(|e| unsafe { CStr::from_ptr(e.extension_name.as_ptr()) }.to_string_lossy().into_owned())
            .collect();
        let has = |e: &str| exts.iter().any(|x| x == e);
        let mut caps = as_caps(instance, physical, &has);
        caps.ray_query = caps.acceleration_structure && props.api_version >= vk::API_VERSION_1_2 && ray_query_feature(instance, physical, &has);
        caps.ptlas = caps.acceleration_structure && has(PTLAS_EXTENSION);
        let family = compute_family(instance, physical, &props, &mut caps)?;
        let device = create_device(instance, physical, family, &caps, &has)?;
        // SAFETY: a live device; everything created here is destroyed by `destroy`.
        unsafe {
            let queue = device.get_device_queue(family, 0);
            let pool = device
                .create_command_pool(
                    &vk::CommandPoolCreateInfo::default()
                        .queue_family_index(family)
                        .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER),
                    None,
                )
                .map_err(vk_err("vkCreateCommandPool"))?;
            let ext = ash::khr::acceleration_structure::Device::new(instance, &device);
            let deferred = ash::khr::deferred_host_operations::Device::new(instance, &device);
            let bda = ash::khr::buffer_device_address::Device::new(instance, &device);
            let mem = instance.get_physical_device_memory_properties(physical);
            Ok(Gpu {
                device,
                name,
                driver_version,
                label,
                queue,
                pool,
                caps,
                ext,
                deferred,
                bda,
                get_device_proc_addr: instance.fp_v1_0().get_device_proc_addr,
                mem,
            })
        }
    }

    pub fn destroy(self) {
        // SAFETY: all objects of this device were destroyed by their arenas; idle first.
        unsafe {
            let _ = self.device.device_wait_idle();
            self.device.destroy_command_pool(self.pool, None);
            self.device.destroy_device(None);
        }
    }

    fn memory_type(&self, bits: u32, place: Place) -> Option<u32> {
        let find = |want: vk::MemoryPropertyFlags| {
            (0..self.mem.memory_type_count)
                .find(|&i| bits & (1 << i) != 0 && self.mem.memory_types[i as usize].property_flags.contains(want))
        };
        match place {
            Place::Device => find(vk::MemoryPropertyFlags::DEVICE_LOCAL).or_else(|| find(vk::MemoryPropertyFlags::empty())),
            Place::Host => find(vk::MemoryPropertyFlags::HOST_VISIBLE | vk::MemoryPropertyFlags::HOST_COHERENT | vk::MemoryPropertyFlags::HOST_CACHED)
                .or_else(|| find(vk::MemoryPropertyFlags::HOST_VISIBLE | vk::MemoryPropertyFlags::HOST_COHERENT)),
        }
    }

    /// A buffer usable in every AS role, with a device address.
    pub fn create_buffer(&self, size: u64, place: Place) -> Result<Buf, String> {
        let size = size.max(16);
        // SAFETY: valid create infos; the caller destroys the buffer (Arena).
        unsafe {
            let buffer = self
                .device
                .create_buffer(&vk::BufferCreateInfo::default().size(size).usage(ALL_USAGE), None)
                .map_err(vk_err("vkCreateBuffer"))?;
            let req = self.device.get_buffer_memory_requirements(buffer);
            let Some(ty) = self.memory_type(req.memory_type_bits, place) else {
                self.device.destroy_buffer(buffer, None);
                return Err(format!("no memory type for a {place:?} buffer"));
            };
            let mut flags = vk::MemoryAllocateFlagsInfo::default().flags(vk::MemoryAllocateFlags::DEVICE_ADDRESS);
            let ai = vk::MemoryAllocateInfo::default().allocation_size(req.size).memory_type_index(ty).push_next(&mut flags);
            let memory = match self.device.allocate_memory(&ai, None) {
                Ok(m) => m,
                Err(e) => {
                    self.device.destroy_buffer(buffer, None);
                    return Err(format!("vkAllocateMemory({} bytes): {e}", req.size));
                }
            };
            self.device.bind_buffer_memory(buffer, memory, 0).map_err(vk_err("vkBindBufferMemory"))?;
            let host_visible = self.mem.memory_types[ty as usize].property_flags.contains(vk::MemoryPropertyFlags::HOST_VISIBLE);
            let ptr = if host_visible {
                self.device.map_memory(memory, 0, vk::WHOLE_SIZE, vk::MemoryMapFlags::empty()).map_err(vk_err("vkMapMemory"))? as *mut u8
            } else {
                std::ptr::null_mut()
            };
            let address = self.bda.get_buffer_device_address(&vk::BufferDeviceAddressInfo::default().buffer(buffer));
            Ok(Buf { buffer, memory, ptr, address, size })
        }
    }

    pub fn destroy_buffer(&self, b: Buf) {
        // SAFETY: the buffer is no longer used by pending work (callers wait first).
        unsafe {
            self.device.destroy_buffer(b.buffer, None);
            self.device.free_memory(b.memory, None);
        }
    }

    /// Record with `f`, submit and wait; returns the wall time of submit + wait in ms.
    pub fn submit(&self, f: impl FnOnce(vk::CommandBuffer)) -> Result<f64, String> {
        let d = &self.device;
        // SAFETY: valid pool and fence; the command buffer is freed after the wait.
        unsafe {
            let cb = d
                .allocate_command_buffers(&vk::CommandBufferAllocateInfo::default().command_pool(self.pool).command_buffer_count(1))
                .map_err(vk_err("vkAllocateCommandBuffers"))?[0];
            d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default().flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT))
                .map_err(vk_err("vkBeginCommandBuffer"))?;
            f(cb);
            d.end_command_buffer(cb).map_err(vk_err("vkEndCommandBuffer"))?;
            let fence = d.create_fence(&vk::FenceCreateInfo::default(), None).map_err(vk_err("vkCreateFence"))?;
            let cbs = [cb];
            let t0 = Instant::now();
            let r = d
                .queue_submit(self.queue, &[vk::SubmitInfo::default().command_buffers(&cbs)], fence)
                .and_then(|_| d.wait_for_fences(&[fence], true, u64::MAX));
            let ms = t0.elapsed().as_secs_f64() * 1e3;
            d.destroy_fence(fence, None);
            d.free_command_buffers(self.pool, &cbs);
            r.map_err(vk_err("vkQueueSubmit/vkWaitForFences"))?;
            Ok(ms)
        }
    }

    /// Milliseconds between the two timestamps of `qp` (None where they cannot be read).
    fn timestamps_ms(&self, qp: vk::QueryPool) -> Option<f64> {
        let mut v = [0u64; 2];
        // SAFETY: a live query pool of this device with two timestamp queries, written by a
        // submission that has completed.
        unsafe { self.device.get_query_pool_results(qp, 0, &mut v, vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT) }.ok()?;
        let mask = self.caps.timestamp_mask;
        let ticks = (v[1] & mask).wrapping_sub(v[0] & mask) & mask;
        Some(ticks as f64 * self.caps.timestamp_period_ns * 1e-6)
    }

    /// Record `body` once between two timestamps (where the queue has them), submit it
    /// `warmup + repeat` times and return the (timestamp ms, fence wall ms) of the timed runs.
    pub fn timed(&self, warmup: usize, repeat: usize, body: impl FnOnce(vk::CommandBuffer)) -> Result<Vec<(Option<f64>, f64)>, String> {
        let d = &self.device;
        // SAFETY: valid objects; everything created here is destroyed before returning.
        unsafe {
            let qp = if self.caps.timestamps {
                Some(
                    d.create_query_pool(&vk::QueryPoolCreateInfo::default().query_type(vk::QueryType::TIMESTAMP).query_count(2), None)
                        .map_err(vk_err("vkCreateQueryPool"))?,
                )
            } else {
                None
            };
            let cb = d
                .allocate_command_buffers(&vk::CommandBufferAllocateInfo::default().command_pool(self.pool).command_buffer_count(1))
                .map_err(vk_err("vkAllocateCommandBuffers"))?[0];
            d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default()).map_err(vk_err("vkBeginCommandBuffer"))?;
            // Earlier submissions (inputs, previous repeats) before this one's AS work.
            let barrier = vk::MemoryBarrier::default()
                .src_access_mask(vk::AccessFlags::MEMORY_WRITE)
                .dst_access_mask(vk::AccessFlags::MEMORY_READ | vk::AccessFlags::MEMORY_WRITE);
            d.cmd_pipeline_barrier(
                cb,
                vk::PipelineStageFlags::ALL_COMMANDS,
                vk::PipelineStageFlags::ALL_COMMANDS,
                vk::DependencyFlags::empty(),
                &[barrier],
                &[],
                &[],
            );
            if let Some(qp) = qp {
                d.cmd_reset_query_pool(cb, qp, 0, 2);
                d.cmd_write_timestamp(cb, vk::PipelineStageFlags::TOP_OF_PIPE, qp, 0);
            }
            body(cb);
            if let Some(qp) = qp {
                d.cmd_write_timestamp(cb, vk::PipelineStageFlags::BOTTOM_OF_PIPE, qp, 1);
            }
            d.end_command_buffer(cb).map_err(vk_err("vkEndCommandBuffer"))?;
            let fence = d.create_fence(&vk::FenceCreateInfo::default(), None).map_err(vk_err("vkCreateFence"))?;
            let cbs = [cb];
            let mut out = Vec::with_capacity(repeat);
            let mut failure = None;
            for k in 0..warmup + repeat {
                let t0 = Instant::now();
                let r = d
                    .queue_submit(self.queue, &[vk::SubmitInfo::default().command_buffers(&cbs)], fence)
                    .and_then(|_| d.wait_for_fences(&[fence], true, u64::MAX));
                let wall = t0.elapsed().as_secs_f64() * 1e3;
                if let Err(e) = r {
                    failure = Some(format!("vkQueueSubmit/vkWaitForFences: {e}"));
                    break;
                }
                let _ = d.reset_fences(&[fence]);
                let ts = qp.and_then(|qp| self.timestamps_ms(qp));
                if k >= warmup {
                    out.push((ts, wall));
                }
            }
            let _ = d.device_wait_idle();
            d.destroy_fence(fence, None);
            d.free_command_buffers(self.pool, &cbs);
            if let Some(qp) = qp {
                d.destroy_query_pool(qp, None);
            }
            match failure {
                Some(f) => Err(f),
                None => Ok(out),
            }
        }
    }
}

/// The driver's version as the report shows it: its own version text where the driver has
/// VkPhysicalDeviceDriverProperties (core in 1.2), else decoded from `driverVersion`.
fn driver_version(instance: &ash::Instance, physical: vk::PhysicalDevice, props: &vk::PhysicalDeviceProperties) -> String {
    let dv = props.driver_version;
    let mut driver_version = if props.vendor_id == 0x10DE {
        format!("{}.{}", dv >> 22, (dv >> 14) & 0xFF)
    } else {
        format!("{}.{}.{}", vk::api_version_major(dv), vk::api_version_minor(dv), vk::api_version_patch(dv))
    };
    if props.api_version >= vk::API_VERSION_1_2 {
        let mut dp = vk::PhysicalDeviceDriverProperties::default();
        let mut p2 = vk::PhysicalDeviceProperties2::default().push_next(&mut dp);
        // SAFETY: plain query into a valid chain; the strings are NUL-terminated by the driver.
        let (name, info) = unsafe {
            instance.get_physical_device_properties2(physical, &mut p2);
            (
                CStr::from_ptr(dp.driver_name.as_ptr()).to_string_lossy().into_owned(),
                CStr::from_ptr(dp.driver_info.as_ptr()).to_string_lossy().into_owned(),
            )
        };
        if !name.is_empty() || !info.is_empty() {
            driver_version = format!("{name} {info}").trim().to_string();
        }
    }
    driver_version
}

/// The acceleration-structure extensions, features and limits the driver has (`has`: whether
/// it offers a device extension). Timestamps are filled in by `compute_family`.
fn as_caps(instance: &ash::Instance, physical: vk::PhysicalDevice, has: &dyn Fn(&str) -> bool) -> Caps {
    let mut caps = Caps::default();
    let mut missing = Vec::new();
    for e in ["VK_KHR_acceleration_structure", "VK_KHR_buffer_device_address", "VK_KHR_deferred_host_operations"] {
        if !has(e) {
            missing.push(e);
        }
    }
    let mut asf = vk::PhysicalDeviceAccelerationStructureFeaturesKHR::default();
    let mut bdaf = vk::PhysicalDeviceBufferDeviceAddressFeatures::default();
    if missing.is_empty() {
        let mut f2 = vk::PhysicalDeviceFeatures2::default().push_next(&mut asf).push_next(&mut bdaf);
        // SAFETY: plain query into a valid chain (both extensions are offered).
        unsafe { instance.get_physical_device_features2(physical, &mut f2) };
        if asf.acceleration_structure == vk::FALSE {
            missing.push("accelerationStructure feature");
        }
        if bdaf.buffer_device_address == vk::FALSE {
            missing.push("bufferDeviceAddress feature");
        }
    }
    caps.acceleration_structure = missing.is_empty();
    caps.missing = (!missing.is_empty()).then(|| format!("missing {}", missing.join(", ")));
    caps.host_commands = caps.acceleration_structure && asf.acceleration_structure_host_commands == vk::TRUE;
    caps.indirect_build = caps.acceleration_structure && asf.acceleration_structure_indirect_build == vk::TRUE;
    caps.deferred = has("VK_KHR_deferred_host_operations");
    if caps.acceleration_structure {
        let mut asp = vk::PhysicalDeviceAccelerationStructurePropertiesKHR::default();
        let mut p2 = vk::PhysicalDeviceProperties2::default().push_next(&mut asp);
        // SAFETY: plain query into a valid chain (the extension is offered).
        unsafe { instance.get_physical_device_properties2(physical, &mut p2) };
        caps.max_primitive_count = asp.max_primitive_count;
        caps.max_instance_count = asp.max_instance_count;
    }
    caps
}

/// Whether the driver offers VK_KHR_ray_query with its rayQuery feature.
fn ray_query_feature(instance: &ash::Instance, physical: vk::PhysicalDevice, has: &dyn Fn(&str) -> bool) -> bool {
    if !has("VK_KHR_ray_query") {
        return false;
    }
    let mut rq = vk::PhysicalDeviceRayQueryFeaturesKHR::default();
    let mut f2 = vk::PhysicalDeviceFeatures2::default().push_next(&mut rq);
    // SAFETY: plain query into a valid chain (the extension is offered).
    unsafe { instance.get_physical_device_features2(physical, &mut f2) };
    rq.ray_query == vk::TRUE
}

/// The first queue family with compute (AS builds are compute-queue commands); its timestamp
/// support goes into `caps`.
fn compute_family(instance: &ash::Instance, physical: vk::PhysicalDevice, props: &vk::PhysicalDeviceProperties, caps: &mut Caps) -> Result<u32, String> {
    // SAFETY: plain query.
    let families = unsafe { instance.get_physical_device_queue_family_properties(physical) };
    let family = families
        .iter()
        .position(|q| q.queue_flags.contains(vk::QueueFlags::COMPUTE))
        .ok_or("no compute queue family")? as u32;
    let bits = families[family as usize].timestamp_valid_bits;
    caps.timestamps = bits > 0 && props.limits.timestamp_period > 0.0;
    caps.timestamp_mask = if bits >= 64 { u64::MAX } else { (1u64 << bits) - 1 };
    caps.timestamp_period_ns = props.limits.timestamp_period as f64;
    Ok(family)
}

/// The device: one queue of `family`, and where the AS work can run, its extensions (those the
/// driver offers) and features.
fn create_device(
    instance: &ash::Instance,
    physical: vk::PhysicalDevice,
    family: u32,
    caps: &Caps,
    has: &dyn Fn(&str) -> bool,
) -> Result<ash::Device, String> {
    let mut names: Vec<&CStr> = Vec::new();
    if caps.acceleration_structure {
        for e in [
            ash::khr::acceleration_structure::NAME,
            ash::khr::deferred_host_operations::NAME,
            ash::khr::buffer_device_address::NAME,
            ash::ext::descriptor_indexing::NAME,
            crate::work::clusters::EXTENSION,
        ] {
            if has(e.to_str().unwrap_or("")) {
                names.push(e);
            }
        }
    }
    if caps.ray_query {
        names.push(ash::khr::ray_query::NAME);
    }
    if caps.ptlas {
        names.push(c"VK_NV_partitioned_acceleration_structure");
    }
    let name_ptrs: Vec<*const std::ffi::c_char> = names.iter().map(|c| c.as_ptr()).collect();
    let prio = [1.0f32];
    let qci = [vk::DeviceQueueCreateInfo::default().queue_family_index(family).queue_priorities(&prio)];
    let mut asf_on = vk::PhysicalDeviceAccelerationStructureFeaturesKHR::default()
        .acceleration_structure(true)
        .acceleration_structure_host_commands(caps.host_commands)
        .acceleration_structure_indirect_build(caps.indirect_build);
    let mut bda_on = vk::PhysicalDeviceBufferDeviceAddressFeatures::default().buffer_device_address(true);
    let mut dci = vk::DeviceCreateInfo::default().queue_create_infos(&qci).enabled_extension_names(&name_ptrs);
    if caps.acceleration_structure {
        dci = dci.push_next(&mut asf_on).push_next(&mut bda_on);
    }
    let mut rq_on = vk::PhysicalDeviceRayQueryFeaturesKHR::default().ray_query(true);
    if caps.ray_query {
        dci = dci.push_next(&mut rq_on);
    }
    let ptlas_on = PtlasFeatures { s_type: vk::StructureType::from_raw(1_000_570_000), p_next: dci.p_next, partitioned_acceleration_structure: vk::TRUE };
    if caps.ptlas {
        dci.p_next = (&ptlas_on as *const PtlasFeatures).cast();
    }
    // VkPhysicalDeviceClusterAccelerationStructureFeaturesNV has the same shape: sType, pNext, one Bool32.
    let clusters_on = PtlasFeatures { s_type: vk::StructureType::from_raw(1_000_569_000), p_next: dci.p_next, partitioned_acceleration_structure: vk::TRUE };
    if names.contains(&crate::work::clusters::EXTENSION) {
        dci.p_next = (&clusters_on as *const PtlasFeatures).cast();
    }
    // SAFETY: valid create info; the caller destroys the device (`Gpu::destroy`).
    unsafe { instance.create_device(physical, &dci, None) }.map_err(vk_err("vkCreateDevice"))
}

/// Owns the buffers and structures of one workload; everything is destroyed on drop.
pub struct Arena<'g> {
    pub gpu: &'g Gpu,
    bufs: RefCell<Vec<Buf>>,
    structures: RefCell<Vec<vk::AccelerationStructureKHR>>,
}

impl<'g> Arena<'g> {
    pub fn new(gpu: &'g Gpu) -> Self {
        Arena { gpu, bufs: Default::default(), structures: Default::default() }
    }

    pub fn buffer(&self, size: u64, place: Place) -> Result<Buf, String> {
        let b = self.gpu.create_buffer(size, place)?;
        self.bufs.borrow_mut().push(b);
        Ok(b)
    }

    /// A device buffer holding `data` (written directly when mapped, else through a staging copy).
    pub fn upload(&self, data: &[u8]) -> Result<Buf, String> {
        let b = self.buffer(data.len() as u64, Place::Device)?;
        if !b.ptr.is_null() {
            // SAFETY: mapped memory of at least data.len() bytes.
            unsafe { std::ptr::copy_nonoverlapping(data.as_ptr(), b.ptr, data.len()) };
        } else {
            let staging = self.gpu.create_buffer(data.len() as u64, Place::Host)?;
            // SAFETY: mapped memory of at least data.len() bytes.
            unsafe { std::ptr::copy_nonoverlapping(data.as_ptr(), staging.ptr, data.len()) };
            let r = self.gpu.submit(|cb| {
                let region = [vk::BufferCopy::default().size(data.len() as u64)];
                // SAFETY: recording command buffer, valid buffers.
                unsafe { self.gpu.device.cmd_copy_buffer(cb, staging.buffer, b.buffer, &region) };
            });
            self.gpu.destroy_buffer(staging);
            r?;
        }
        Ok(b)
    }

    /// An acceleration structure of `size` bytes in a buffer of its own.
    pub fn structure(&self, ty: vk::AccelerationStructureTypeKHR, size: u64, place: Place) -> Result<(vk::AccelerationStructureKHR, Buf), String> {
        let b = self.buffer(size, place)?;
        let info = vk::AccelerationStructureCreateInfoKHR::default().buffer(b.buffer).size(size).ty(ty);
        // SAFETY: valid create info.
        let s = unsafe { self.gpu.ext.create_acceleration_structure(&info, None) }.map_err(vk_err("vkCreateAccelerationStructureKHR"))?;
        self.structures.borrow_mut().push(s);
        Ok((s, b))
    }

    pub fn address_of(&self, s: vk::AccelerationStructureKHR) -> u64 {
        // SAFETY: live structure.
        unsafe {
            self.gpu
                .ext
                .get_acceleration_structure_device_address(&vk::AccelerationStructureDeviceAddressInfoKHR::default().acceleration_structure(s))
        }
    }

    /// One property through a query pool (device command) and vkGetQueryPoolResults.
    pub fn query(&self, s: vk::AccelerationStructureKHR, ty: vk::QueryType) -> Result<u64, String> {
        let d = &self.gpu.device;
        // SAFETY: valid create info; pool destroyed below.
        let pool = unsafe { d.create_query_pool(&vk::QueryPoolCreateInfo::default().query_type(ty).query_count(1), None) }
            .map_err(vk_err("vkCreateQueryPool"))?;
        let r = self.gpu.submit(|cb| {
            // SAFETY: recording command buffer, valid pool and structure.
            unsafe {
                d.cmd_reset_query_pool(cb, pool, 0, 1);
                self.gpu.ext.cmd_write_acceleration_structures_properties(cb, &[s], ty, pool, 0);
            }
        });
        let mut out = [0u64; 1];
        // SAFETY: valid pool.
        let q = unsafe { d.get_query_pool_results(pool, 0, &mut out, vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT) };
        // SAFETY: the submission above has completed.
        unsafe { d.destroy_query_pool(pool, None) };
        r?;
        q.map_err(vk_err("vkGetQueryPoolResults"))?;
        Ok(out[0])
    }

    /// Serialize a structure (device command) into host-visible memory and return the bytes.
    pub fn serialize(&self, s: vk::AccelerationStructureKHR) -> Result<Vec<u8>, String> {
        let size = self.query(s, vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_SIZE_KHR)?;
        let b = self.buffer(size, Place::Host)?;
        self.gpu.submit(|cb| {
            let info = vk::CopyAccelerationStructureToMemoryInfoKHR::default()
                .src(s)
                .dst(vk::DeviceOrHostAddressKHR { device_address: b.address })
                .mode(vk::CopyAccelerationStructureModeKHR::SERIALIZE);
            // SAFETY: valid info, recording command buffer.
            unsafe { self.gpu.ext.cmd_copy_acceleration_structure_to_memory(cb, &info) };
        })?;
        Ok(b.read(0, size as usize))
    }
}

impl Drop for Arena<'_> {
    fn drop(&mut self) {
        let d = &self.gpu.device;
        // SAFETY: wait for the queue; then every object is destroyed once.
        unsafe {
            let _ = d.queue_wait_idle(self.gpu.queue);
            for s in self.structures.borrow().iter() {
                self.gpu.ext.destroy_acceleration_structure(*s, None);
            }
            for b in self.bufs.borrow().iter() {
                d.destroy_buffer(b.buffer, None);
                d.free_memory(b.memory, None);
            }
        }
    }
}

/// The structure bytes inside an Arbor serialization (after the 56-byte header and N addresses).
pub fn payload(serialized: &[u8]) -> Option<&[u8]> {
    let n = u64::from_le_bytes(serialized.get(48..56)?.try_into().ok()?) as usize;
    serialized.get(56 + 8 * n..)
}
