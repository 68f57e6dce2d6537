//! Descriptor set layouts, pools, sets, updates, templates and pipeline layouts through the real
//! loader with validation on. What a set stores is not observable through the API without
//! shaders; `runtime::descriptor`'s unit tests read it back. Here: every command's results and
//! return codes, pool exhaustion, and Arbor's own diagnostics for invalid updates.
mod harness;

use std::ffi::CString;

use ash::vk;

const SB: vk::DescriptorType = vk::DescriptorType::STORAGE_BUFFER;
const UB: vk::DescriptorType = vk::DescriptorType::UNIFORM_BUFFER;

fn layout_binding(binding: u32, t: vk::DescriptorType, count: u32) -> vk::DescriptorSetLayoutBinding<'static> {
    vk::DescriptorSetLayoutBinding::default()
        .binding(binding)
        .descriptor_type(t)
        .descriptor_count(count)
        .stage_flags(vk::ShaderStageFlags::COMPUTE)
}

/// Layout: binding 0 = 2 storage buffers, binding 1 = 1 uniform buffer, binding 2 = 1 dynamic
/// storage buffer.
fn basic_layout(device: &ash::Device) -> vk::DescriptorSetLayout {
    let bindings = [layout_binding(0, SB, 2), layout_binding(1, UB, 1), layout_binding(2, vk::DescriptorType::STORAGE_BUFFER_DYNAMIC, 1)];
    // SAFETY: valid create info.
    unsafe { device.create_descriptor_set_layout(&vk::DescriptorSetLayoutCreateInfo::default().bindings(&bindings), None) }.unwrap()
}

#[test]
fn pools_allocate_until_out_of_pool_memory() {
    let ctx = harness::context();
    let d = &ctx.device;
    // SAFETY: valid create infos; everything destroyed below.
    unsafe {
        let layout = basic_layout(d);
        let mut support_info = vk::DescriptorSetLayoutSupport::default();
        let bindings = [layout_binding(0, SB, 2), layout_binding(1, UB, 1)];
        d.get_descriptor_set_layout_support(&vk::DescriptorSetLayoutCreateInfo::default().bindings(&bindings), &mut support_info);
        assert_eq!(support_info.supported, vk::TRUE);

        // Room for exactly two sets' storage buffers (2 + 2 of 5).
        let sizes = [
            vk::DescriptorPoolSize { ty: SB, descriptor_count: 5 },
            vk::DescriptorPoolSize { ty: UB, descriptor_count: 3 },
            vk::DescriptorPoolSize { ty: vk::DescriptorType::STORAGE_BUFFER_DYNAMIC, descriptor_count: 3 },
        ];
        let pool = d
            .create_descriptor_pool(
                &vk::DescriptorPoolCreateInfo::default().max_sets(3).pool_sizes(&sizes).flags(vk::DescriptorPoolCreateFlags::FREE_DESCRIPTOR_SET),
                None,
            )
            .unwrap();
        let one = [layout];
        let alloc = vk::DescriptorSetAllocateInfo::default().descriptor_pool(pool).set_layouts(&one);
        let a = d.allocate_descriptor_sets(&alloc).unwrap();
        let b = d.allocate_descriptor_sets(&alloc).unwrap();
        assert_ne!(a[0], b[0]);
        assert_eq!(d.allocate_descriptor_sets(&alloc), Err(vk::Result::ERROR_OUT_OF_POOL_MEMORY));
        // Freeing gives the descriptors back.
        d.free_descriptor_sets(pool, &a).unwrap();
        let c = d.allocate_descriptor_sets(&alloc).unwrap();
        assert_eq!(d.allocate_descriptor_sets(&alloc), Err(vk::Result::ERROR_OUT_OF_POOL_MEMORY));
        // Resetting frees every set (b and c are gone).
        d.reset_descriptor_pool(pool, vk::DescriptorPoolResetFlags::empty()).unwrap();
        let two = [layout, layout];
        let both = d.allocate_descriptor_sets(&vk::DescriptorSetAllocateInfo::default().descriptor_pool(pool).set_layouts(&two)).unwrap();
        assert_eq!(both.len(), 2);
        let _ = (b, c);
        d.destroy_descriptor_pool(pool, None);

        // maxSets is enforced too.
        let empty = d.create_descriptor_set_layout(&vk::DescriptorSetLayoutCreateInfo::default(), None).unwrap();
        let sizes = [vk::DescriptorPoolSize { ty: SB, descriptor_count: 1 }];
        let pool = d.create_descriptor_pool(&vk::DescriptorPoolCreateInfo::default().max_sets(2).pool_sizes(&sizes), None).unwrap();
        let e = [empty];
        let alloc = vk::DescriptorSetAllocateInfo::default().descriptor_pool(pool).set_layouts(&e);
        d.allocate_descriptor_sets(&alloc).unwrap();
        d.allocate_descriptor_sets(&alloc).unwrap();
        assert_eq!(d.allocate_descriptor_sets(&alloc), Err(vk::Result::ERROR_OUT_OF_POOL_MEMORY));
        // Destroying the pool frees its sets.
        d.destroy_descriptor_pool(pool, None);
        d.destroy_descriptor_set_layout(empty, None);
        d.destroy_descriptor_set_layout(layout, None);
        d.destroy_descriptor_pool(vk::DescriptorPool::null(), None);
    }
    ctx.finish();
}

// One function: one scenario, writes, a copy and a template on the same two sets, checked at the end.
#[test]
fn writes_copies_and_templates() {
    let ctx = harness::context();
    let d = &ctx.device;
    let (storage, storage_mem, _) = ctx.host_buffer(4096, vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::UNIFORM_BUFFER);
    // SAFETY: valid create infos and updates; everything destroyed below.
    unsafe {
        let layout = basic_layout(d);
        let sizes = [
            vk::DescriptorPoolSize { ty: SB, descriptor_count: 8 },
            vk::DescriptorPoolSize { ty: UB, descriptor_count: 4 },
            vk::DescriptorPoolSize { ty: vk::DescriptorType::STORAGE_BUFFER_DYNAMIC, descriptor_count: 4 },
        ];
        let pool = d.create_descriptor_pool(&vk::DescriptorPoolCreateInfo::default().max_sets(4).pool_sizes(&sizes), None).unwrap();
        let layouts = [layout, layout];
        let sets = d.allocate_descriptor_sets(&vk::DescriptorSetAllocateInfo::default().descriptor_pool(pool).set_layouts(&layouts)).unwrap();

        let sb_infos = [
            vk::DescriptorBufferInfo { buffer: storage, offset: 0, range: 256 },
            vk::DescriptorBufferInfo { buffer: storage, offset: 256, range: vk::WHOLE_SIZE },
        ];
        let ub_info = [vk::DescriptorBufferInfo { buffer: storage, offset: 1024, range: 64 }];
        let dyn_info = [vk::DescriptorBufferInfo { buffer: storage, offset: 0, range: 512 }];
        let writes = [
            vk::WriteDescriptorSet::default().dst_set(sets[0]).dst_binding(0).descriptor_type(SB).buffer_info(&sb_infos),
            vk::WriteDescriptorSet::default().dst_set(sets[0]).dst_binding(1).descriptor_type(UB).buffer_info(&ub_info),
            vk::WriteDescriptorSet::default()
                .dst_set(sets[0])
                .dst_binding(2)
                .descriptor_type(vk::DescriptorType::STORAGE_BUFFER_DYNAMIC)
                .buffer_info(&dyn_info),
        ];
        let copies = [vk::CopyDescriptorSet::default()
            .src_set(sets[0])
            .src_binding(0)
            .dst_set(sets[1])
            .dst_binding(0)
            .descriptor_count(2)];
        d.update_descriptor_sets(&writes, &copies);

        // A template writing binding 0 from an application struct with its own layout.
        #[repr(C)]
        struct Data {
            _tag: u32,
            infos: [vk::DescriptorBufferInfo; 2],
        }
        let entries = [vk::DescriptorUpdateTemplateEntry {
            dst_binding: 0,
            dst_array_element: 0,
            descriptor_count: 2,
            descriptor_type: SB,
            offset: std::mem::offset_of!(Data, infos),
            stride: std::mem::size_of::<vk::DescriptorBufferInfo>(),
        }];
        let template = d
            .create_descriptor_update_template(
                &vk::DescriptorUpdateTemplateCreateInfo::default()
                    .descriptor_update_entries(&entries)
                    .template_type(vk::DescriptorUpdateTemplateType::DESCRIPTOR_SET)
                    .descriptor_set_layout(layout),
                None,
            )
            .unwrap();
        let data = Data { _tag: 7, infos: [sb_infos[1], sb_infos[0]] };
        d.update_descriptor_set_with_template(sets[1], template, &data as *const Data as *const std::ffi::c_void);
        d.destroy_descriptor_update_template(template, None);

        // A pipeline layout with both set layouts and a push-constant range.
        let ranges = [vk::PushConstantRange { stage_flags: vk::ShaderStageFlags::COMPUTE, offset: 0, size: 64 }];
        let pl = d
            .create_pipeline_layout(&vk::PipelineLayoutCreateInfo::default().set_layouts(&layouts).push_constant_ranges(&ranges), None)
            .unwrap();
        d.destroy_pipeline_layout(pl, None);

        d.destroy_descriptor_pool(pool, None);
        d.destroy_descriptor_set_layout(layout, None);
        d.destroy_buffer(storage, None);
        d.free_memory(storage_mem, None);
    }
    ctx.finish();
    let diag = harness::diagnostics();
    for cmd in ["vkUpdateDescriptorSetWithTemplate", "vkCreateDescriptorUpdateTemplate", "vkCreatePipelineLayout"] {
        assert!(!diag.contains(cmd), "Arbor reported a problem with {cmd}:\n{diag}");
    }
}

/// A device with VK_EXT_descriptor_indexing and the features Arbor offers for it.
fn indexing_device(ctx: &harness::Context) -> ash::Device {
    let exts: Vec<CString> = ["VK_KHR_maintenance3", "VK_EXT_descriptor_indexing"].iter().map(|e| CString::new(*e).unwrap()).collect();
    let ext_p: Vec<*const i8> = exts.iter().map(|c| c.as_ptr()).collect();
    let prio = [1.0f32];
    let qci = [vk::DeviceQueueCreateInfo::default().queue_family_index(0).queue_priorities(&prio)];
    let mut indexing = vk::PhysicalDeviceDescriptorIndexingFeatures::default()
        .descriptor_binding_storage_buffer_update_after_bind(true)
        .descriptor_binding_uniform_buffer_update_after_bind(true)
        .descriptor_binding_partially_bound(true)
        .descriptor_binding_variable_descriptor_count(true)
        .descriptor_binding_update_unused_while_pending(true)
        .runtime_descriptor_array(true);
    let ci = vk::DeviceCreateInfo::default().queue_create_infos(&qci).enabled_extension_names(&ext_p).push_next(&mut indexing);
    // SAFETY: valid create info.
    unsafe { ctx.instance.create_device(ctx.physical, &ci, None) }.expect("device with descriptor indexing")
}

#[test]
fn binding_flags_update_after_bind_and_variable_counts() {
    let ctx = harness::context();
    let d = indexing_device(&ctx);
    // SAFETY: valid create infos; everything destroyed below, the device last.
    unsafe {
        let bindings = [layout_binding(0, UB, 1), layout_binding(1, SB, 1000)];
        let flags = [
            vk::DescriptorBindingFlags::UPDATE_AFTER_BIND,
            vk::DescriptorBindingFlags::UPDATE_AFTER_BIND
                | vk::DescriptorBindingFlags::PARTIALLY_BOUND
                | vk::DescriptorBindingFlags::VARIABLE_DESCRIPTOR_COUNT,
        ];
        let mut flags_info = vk::DescriptorSetLayoutBindingFlagsCreateInfo::default().binding_flags(&flags);
        let ci = vk::DescriptorSetLayoutCreateInfo::default()
            .flags(vk::DescriptorSetLayoutCreateFlags::UPDATE_AFTER_BIND_POOL)
            .bindings(&bindings)
            .push_next(&mut flags_info);
        let mut variable_support = vk::DescriptorSetVariableDescriptorCountLayoutSupport::default();
        let mut support_info = vk::DescriptorSetLayoutSupport::default().push_next(&mut variable_support);
        d.get_descriptor_set_layout_support(&ci, &mut support_info);
        assert_eq!(support_info.supported, vk::TRUE);
        assert!(variable_support.max_variable_descriptor_count >= 1000);
        let layout = d.create_descriptor_set_layout(&ci, None).unwrap();

        let sizes = [vk::DescriptorPoolSize { ty: SB, descriptor_count: 100 }, vk::DescriptorPoolSize { ty: UB, descriptor_count: 4 }];
        let pool = d
            .create_descriptor_pool(
                &vk::DescriptorPoolCreateInfo::default().max_sets(4).pool_sizes(&sizes).flags(vk::DescriptorPoolCreateFlags::UPDATE_AFTER_BIND),
                None,
            )
            .unwrap();
        // The pool counts the variable counts, not the binding's maximum of 1000.
        let layouts = [layout, layout];
        let counts = [60u32, 40];
        let mut var = vk::DescriptorSetVariableDescriptorCountAllocateInfo::default().descriptor_counts(&counts);
        let sets = d
            .allocate_descriptor_sets(&vk::DescriptorSetAllocateInfo::default().descriptor_pool(pool).set_layouts(&layouts).push_next(&mut var))
            .unwrap();
        let one = [layout];
        let counts1 = [1u32];
        let mut var1 = vk::DescriptorSetVariableDescriptorCountAllocateInfo::default().descriptor_counts(&counts1);
        assert_eq!(
            d.allocate_descriptor_sets(&vk::DescriptorSetAllocateInfo::default().descriptor_pool(pool).set_layouts(&one).push_next(&mut var1)),
            Err(vk::Result::ERROR_OUT_OF_POOL_MEMORY)
        );

        // Write the last element of the 60-element variable binding.
        let bci = vk::BufferCreateInfo::default().size(1024).usage(vk::BufferUsageFlags::STORAGE_BUFFER);
        let buffer = d.create_buffer(&bci, None).unwrap();
        let req = d.get_buffer_memory_requirements(buffer);
        let mem = d.allocate_memory(&vk::MemoryAllocateInfo::default().allocation_size(req.size).memory_type_index(0), None).unwrap();
        d.bind_buffer_memory(buffer, mem, 0).unwrap();
        let info = [vk::DescriptorBufferInfo { buffer, offset: 0, range: vk::WHOLE_SIZE }];
        let w = [vk::WriteDescriptorSet::default().dst_set(sets[0]).dst_binding(1).dst_array_element(59).descriptor_type(SB).buffer_info(&info)];
        d.update_descriptor_sets(&w, &[]);

        d.destroy_descriptor_pool(pool, None);
        d.destroy_descriptor_set_layout(layout, None);
        d.destroy_buffer(buffer, None);
        d.free_memory(mem, None);
        d.destroy_device(None);
    }
    ctx.finish();
}

/// With the validation layer off, Arbor's own checks report invalid updates (with VUIDs) and
/// skip them; nothing crashes.
#[test]
fn invalid_updates_are_reported() {
    let ctx = harness::Context::new(harness::Options { validation: false, ..Default::default() });
    let d = &ctx.device;
    // SAFETY: deliberately invalid usage that Arbor must survive; objects destroyed below.
    unsafe {
        let (uniform_only, mem, _) = ctx.host_buffer(1024, vk::BufferUsageFlags::UNIFORM_BUFFER);
        let layout = basic_layout(d);
        let sizes = [
            vk::DescriptorPoolSize { ty: SB, descriptor_count: 8 },
            vk::DescriptorPoolSize { ty: UB, descriptor_count: 8 },
            vk::DescriptorPoolSize { ty: vk::DescriptorType::STORAGE_BUFFER_DYNAMIC, descriptor_count: 8 },
        ];
        let pool = d.create_descriptor_pool(&vk::DescriptorPoolCreateInfo::default().max_sets(2).pool_sizes(&sizes), None).unwrap();
        let l = [layout];
        let set = d.allocate_descriptor_sets(&vk::DescriptorSetAllocateInfo::default().descriptor_pool(pool).set_layouts(&l)).unwrap()[0];

        let info = [vk::DescriptorBufferInfo { buffer: uniform_only, offset: 0, range: 64 }];
        // Storage descriptor for a buffer without STORAGE_BUFFER usage.
        d.update_descriptor_sets(&[vk::WriteDescriptorSet::default().dst_set(set).dst_binding(0).descriptor_type(SB).buffer_info(&info)], &[]);
        // Type that does not match the binding.
        d.update_descriptor_sets(&[vk::WriteDescriptorSet::default().dst_set(set).dst_binding(0).descriptor_type(UB).buffer_info(&info)], &[]);
        // Past the last binding.
        let three = [info[0]; 3];
        d.update_descriptor_sets(
            &[vk::WriteDescriptorSet::default().dst_set(set).dst_binding(1).descriptor_type(UB).buffer_info(&three)],
            &[],
        );
        // Freeing from a pool without FREE_DESCRIPTOR_SET.
        assert_eq!(d.free_descriptor_sets(pool, &[set]), Err(vk::Result::ERROR_VALIDATION_FAILED_EXT));

        d.destroy_descriptor_pool(pool, None);
        d.destroy_descriptor_set_layout(layout, None);
        d.destroy_buffer(uniform_only, None);
        d.free_memory(mem, None);
    }
    ctx.finish();
    let diag = harness::diagnostics();
    for vuid in [
        "VUID-VkWriteDescriptorSet-descriptorType-00331",
        "VUID-VkWriteDescriptorSet-descriptorType-00319",
        "VUID-VkWriteDescriptorSet-descriptorCount-00317",
        "VUID-vkFreeDescriptorSets-descriptorPool-00312",
    ] {
        assert!(diag.contains(vuid), "{vuid} not reported:\n{diag}");
    }
}

/// Acceleration-structure descriptors (VkWriteDescriptorSetAccelerationStructureKHR), written
/// directly and through a template.
#[test]
fn acceleration_structure_descriptors() {
    let ctx = harness::Context::new(harness::Options { acceleration_structure: true, ..Default::default() });
    let d = &ctx.device;
    let as_fns = ash::khr::acceleration_structure::Device::new(&ctx.instance, d);
    let (buffer, mem, _) = ctx.host_buffer(
        4096,
        vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS,
    );
    // SAFETY: valid create infos and updates; everything destroyed below.
    unsafe {
        let tlas = as_fns
            .create_acceleration_structure(
                &vk::AccelerationStructureCreateInfoKHR::default()
                    .buffer(buffer)
                    .offset(0)
                    .size(2048)
                    .ty(vk::AccelerationStructureTypeKHR::TOP_LEVEL),
                None,
            )
            .unwrap();
        let t = vk::DescriptorType::ACCELERATION_STRUCTURE_KHR;
        let bindings = [layout_binding(0, t, 2)];
        let layout = d.create_descriptor_set_layout(&vk::DescriptorSetLayoutCreateInfo::default().bindings(&bindings), None).unwrap();
        let sizes = [vk::DescriptorPoolSize { ty: t, descriptor_count: 2 }];
        let pool = d.create_descriptor_pool(&vk::DescriptorPoolCreateInfo::default().max_sets(1).pool_sizes(&sizes), None).unwrap();
        let l = [layout];
        let set = d.allocate_descriptor_sets(&vk::DescriptorSetAllocateInfo::default().descriptor_pool(pool).set_layouts(&l)).unwrap()[0];
        let handles = [tlas];
        let mut as_write = vk::WriteDescriptorSetAccelerationStructureKHR::default().acceleration_structures(&handles);
        let mut w = vk::WriteDescriptorSet::default().dst_set(set).dst_binding(0).dst_array_element(1).descriptor_type(t).push_next(&mut as_write);
        w.descriptor_count = 1;
        d.update_descriptor_sets(&[w], &[]);

        let entries = [vk::DescriptorUpdateTemplateEntry {
            dst_binding: 0,
            dst_array_element: 0,
            descriptor_count: 1,
            descriptor_type: t,
            offset: 0,
            stride: std::mem::size_of::<vk::AccelerationStructureKHR>(),
        }];
        let template = d
            .create_descriptor_update_template(
                &vk::DescriptorUpdateTemplateCreateInfo::default()
                    .descriptor_update_entries(&entries)
                    .template_type(vk::DescriptorUpdateTemplateType::DESCRIPTOR_SET)
                    .descriptor_set_layout(layout),
                None,
            )
            .unwrap();
        d.update_descriptor_set_with_template(set, template, handles.as_ptr() as *const std::ffi::c_void);
        d.destroy_descriptor_update_template(template, None);
        d.destroy_descriptor_pool(pool, None);
        d.destroy_descriptor_set_layout(layout, None);
        as_fns.destroy_acceleration_structure(tlas, None);
        d.destroy_buffer(buffer, None);
        d.free_memory(mem, None);
    }
    ctx.finish();
    let diag = harness::diagnostics();
    assert!(!diag.contains("VkWriteDescriptorSetAccelerationStructureKHR") && !diag.contains("descriptorType-02382"), "{diag}");
}
