//! Instance, physical device and device through the real loader with validation on.
mod harness;

use ash::vk;

#[test]
fn device_properties_through_loader() {
    let ctx = harness::context();
    // SAFETY: plain queries on live objects.
    unsafe {
        let p = ctx.instance.get_physical_device_properties(ctx.physical);
        assert_eq!(p.device_name_as_c_str().unwrap().to_str().unwrap(), "Arbor (software)");
        assert_eq!(p.device_type, vk::PhysicalDeviceType::CPU);
        assert_eq!(vk::api_version_minor(p.api_version), 2);
        let q = ctx.instance.get_physical_device_queue_family_properties(ctx.physical);
        assert_eq!(q.len(), 1);
        assert!(q[0].queue_flags.contains(vk::QueueFlags::COMPUTE | vk::QueueFlags::TRANSFER));
        assert!(!q[0].queue_flags.contains(vk::QueueFlags::GRAPHICS));
        assert!(q[0].queue_flags.contains(vk::QueueFlags::SPARSE_BINDING));
        let f = ctx.instance.get_physical_device_features(ctx.physical);
        assert_eq!(f.sparse_binding, vk::TRUE, "the queue family binds sparse buffers (tests/sparse.rs)");
        assert_eq!(f.sparse_residency_buffer, vk::FALSE, "no partially bound use yet");
        let mut id = vk::PhysicalDeviceIDProperties::default();
        let mut p2 = vk::PhysicalDeviceProperties2::default().push_next(&mut id);
        ctx.instance.get_physical_device_properties2(ctx.physical, &mut p2);
        assert_ne!(id.driver_uuid, [0; 16]);
        assert_ne!(id.device_uuid, [0; 16]);
        let mp = ctx.instance.get_physical_device_memory_properties(ctx.physical);
        assert!(mp.memory_heaps[0].size > 0);
        let fp = ctx.instance.get_physical_device_format_properties(ctx.physical, vk::Format::R32G32B32_SFLOAT);
        assert!(fp.buffer_features.contains(vk::FormatFeatureFlags::ACCELERATION_STRUCTURE_VERTEX_BUFFER_KHR));
    }
    ctx.finish();
}

#[test]
fn stable_uuids_across_instances() {
    let read = || {
        let ctx = harness::context();
        let mut id = vk::PhysicalDeviceIDProperties::default();
        let mut p2 = vk::PhysicalDeviceProperties2::default().push_next(&mut id);
        // SAFETY: plain query.
        unsafe { ctx.instance.get_physical_device_properties2(ctx.physical, &mut p2) };
        ctx.finish();
        (id.driver_uuid, id.device_uuid)
    };
    assert_eq!(read(), read());
}
