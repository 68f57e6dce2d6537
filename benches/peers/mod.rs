//! Peer builders measured beside Arbor in the same run (`--features peers`): Embree 3's generic
//! BVH builder through FFI (Debian `libembree-dev`) and obvhs' PLOC builder. Both produce
//! binary trees whose SAH is computed here with the PEERS.md formula (C_T = C_I = 1).

// Each bench that includes this module uses a different part of it.
#![allow(dead_code)]

use arbor_scene::Mesh;

/// Box as [min x, y, z, max x, y, z].
pub type Bounds = [f32; 6];

pub fn area(b: &Bounds) -> f64 {
    let (dx, dy, dz) = ((b[3] - b[0]).max(0.0) as f64, (b[4] - b[1]).max(0.0) as f64, (b[5] - b[2]).max(0.0) as f64);
    2.0 * (dx * dy + dy * dz + dz * dx)
}

pub fn union(a: &Bounds, b: &Bounds) -> Bounds {
    [a[0].min(b[0]), a[1].min(b[1]), a[2].min(b[2]), a[3].max(b[3]), a[4].max(b[4]), a[5].max(b[5])]
}

pub fn triangle_bounds(m: &Mesh, i: usize) -> Bounds {
    let t = m.triangle(i);
    let mut b = [f32::INFINITY, f32::INFINITY, f32::INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY];
    for p in t {
        for k in 0..3 {
            b[k] = b[k].min(p[k]);
            b[k + 3] = b[k + 3].max(p[k]);
        }
    }
    b
}

pub mod embree {
    //! Minimal FFI to Embree 3.13's generic BVH builder (`rtcore_builder.h`).
    use super::{area, Bounds};
    use arbor_scene::Mesh;
    use std::ffi::{c_char, c_uint, c_void, CString};

    #[repr(C, align(32))]
    #[derive(Clone, Copy, Default)]
    pub struct BuildPrimitive {
        pub lower: [f32; 3],
        pub geom_id: c_uint,
        pub upper: [f32; 3],
        pub prim_id: c_uint,
    }

    #[repr(C, align(16))]
    #[derive(Clone, Copy)]
    pub struct RtcBounds {
        lower: [f32; 3],
        align0: f32,
        upper: [f32; 3],
        align1: f32,
    }

    type CreateNode = unsafe extern "C" fn(*mut c_void, c_uint, *mut c_void) -> *mut c_void;
    type SetChildren = unsafe extern "C" fn(*mut c_void, *mut *mut c_void, c_uint, *mut c_void);
    type SetBounds = unsafe extern "C" fn(*mut c_void, *const *const RtcBounds, c_uint, *mut c_void);
    type CreateLeaf = unsafe extern "C" fn(*mut c_void, *const BuildPrimitive, usize, *mut c_void) -> *mut c_void;
    type SplitPrimitive = unsafe extern "C" fn(*const BuildPrimitive, c_uint, f32, *mut RtcBounds, *mut RtcBounds, *mut c_void);

    #[repr(C)]
    struct BuildArguments {
        byte_size: usize,
        build_quality: c_uint,
        build_flags: c_uint,
        max_branching_factor: c_uint,
        max_depth: c_uint,
        sah_block_size: c_uint,
        min_leaf_size: c_uint,
        max_leaf_size: c_uint,
        traversal_cost: f32,
        intersection_cost: f32,
        bvh: *mut c_void,
        primitives: *mut BuildPrimitive,
        primitive_count: usize,
        primitive_array_capacity: usize,
        create_node: Option<CreateNode>,
        set_node_children: Option<SetChildren>,
        set_node_bounds: Option<SetBounds>,
        create_leaf: Option<CreateLeaf>,
        split_primitive: Option<SplitPrimitive>,
        build_progress: *mut c_void,
        user_ptr: *mut c_void,
    }

    #[link(name = "embree3")]
    extern "C" {
        fn rtcNewDevice(config: *const c_char) -> *mut c_void;
        fn rtcReleaseDevice(device: *mut c_void);
        fn rtcGetDeviceError(device: *mut c_void) -> c_uint;
        fn rtcNewBVH(device: *mut c_void) -> *mut c_void;
        fn rtcReleaseBVH(bvh: *mut c_void);
        fn rtcBuildBVH(args: *const BuildArguments) -> *mut c_void;
        fn rtcThreadLocalAlloc(allocator: *mut c_void, bytes: usize, align: usize) -> *mut c_void;
        fn rtcNewScene(device: *mut c_void) -> *mut c_void;
        fn rtcSetSceneBuildQuality(scene: *mut c_void, quality: c_uint);
        fn rtcReleaseScene(scene: *mut c_void);
        fn rtcAttachGeometry(scene: *mut c_void, geometry: *mut c_void) -> c_uint;
        fn rtcCommitScene(scene: *mut c_void);
        fn rtcNewGeometry(device: *mut c_void, ty: c_uint) -> *mut c_void;
        fn rtcSetSharedGeometryBuffer(geometry: *mut c_void, ty: c_uint, slot: c_uint, format: c_uint, ptr: *const c_void, offset: usize, stride: usize, count: usize);
        fn rtcSetGeometryBuildQuality(geometry: *mut c_void, quality: c_uint);
        fn rtcCommitGeometry(geometry: *mut c_void);
        fn rtcReleaseGeometry(geometry: *mut c_void);
        fn rtcIntersect1(scene: *mut c_void, context: *mut IntersectContext, rayhit: *mut RayHit);
        fn rtcOccluded1(scene: *mut c_void, context: *mut IntersectContext, ray: *mut RtcRay);
    }

    #[repr(C, align(16))]
    #[derive(Clone, Copy, Default)]
    pub struct RtcRay {
        pub org: [f32; 3],
        pub tnear: f32,
        pub dir: [f32; 3],
        pub time: f32,
        pub tfar: f32,
        pub mask: c_uint,
        pub id: c_uint,
        pub flags: c_uint,
    }

    #[repr(C, align(16))]
    #[derive(Clone, Copy, Default)]
    pub struct RtcHit {
        pub ng: [f32; 3],
        pub u: f32,
        pub v: f32,
        pub prim_id: c_uint,
        pub geom_id: c_uint,
        pub inst_id: [c_uint; 1],
    }

    #[repr(C)]
    #[derive(Clone, Copy, Default)]
    pub struct RayHit {
        pub ray: RtcRay,
        pub hit: RtcHit,
    }

    #[repr(C)]
    pub struct IntersectContext {
        flags: c_uint,
        filter: *const c_void,
        inst_id: [c_uint; 1],
    }

    const INVALID_ID: c_uint = u32::MAX;

    fn context() -> IntersectContext {
        IntersectContext { flags: 0, filter: std::ptr::null(), inst_id: [INVALID_ID] }
    }

    /// An Embree scene (its own BVH, rtcCommitScene) over one triangle mesh, for tracing.
    pub struct Scene {
        scene: *mut c_void,
        // Shared buffers must outlive the scene; Embree reads vertices with 16-byte loads, so
        // the vertex buffer has 16 bytes of padding after the last vertex.
        _vertices: Vec<f32>,
        _indices: Vec<u32>,
    }

    // SAFETY: a committed Embree scene may be traced from several threads at once.
    unsafe impl Sync for Scene {}
    // SAFETY: as above.
    unsafe impl Send for Scene {}

    impl Scene {
        pub fn new(device: &Device, mesh: &Mesh, quality: u32) -> Self {
            let mut vertices: Vec<f32> = mesh.positions.iter().flatten().copied().collect();
            vertices.extend_from_slice(&[0.0; 4]);
            let indices: Vec<u32> = mesh.indices.iter().flatten().copied().collect();
            // SAFETY: valid device; buffers alive as long as the scene (owned by Self).
            unsafe {
                let scene = rtcNewScene(device.0);
                rtcSetSceneBuildQuality(scene, quality);
                let g = rtcNewGeometry(device.0, 0 /* TRIANGLE */);
                rtcSetGeometryBuildQuality(g, quality);
                rtcSetSharedGeometryBuffer(g, 1 /* VERTEX */, 0, 0x9003 /* FLOAT3 */, vertices.as_ptr() as *const c_void, 0, 12, mesh.positions.len());
                rtcSetSharedGeometryBuffer(g, 0 /* INDEX */, 0, 0x5003 /* UINT3 */, indices.as_ptr() as *const c_void, 0, 12, mesh.indices.len());
                rtcCommitGeometry(g);
                rtcAttachGeometry(scene, g);
                rtcReleaseGeometry(g);
                rtcCommitScene(scene);
                let err = rtcGetDeviceError(device.0);
                assert!(err == 0, "Embree scene build failed (error {err})");
                Scene { scene, _vertices: vertices, _indices: indices }
            }
        }

        /// Closest hit: (t, primitive) or None.
        pub fn intersect(&self, org: [f32; 3], dir: [f32; 3], tnear: f32, tfar: f32) -> Option<(f32, u32)> {
            let mut rh = RayHit { ray: RtcRay { org, tnear, dir, time: 0.0, tfar, mask: u32::MAX, id: 0, flags: 0 }, hit: RtcHit::default() };
            rh.hit.geom_id = INVALID_ID;
            rh.hit.inst_id = [INVALID_ID];
            let mut ctx = context();
            // SAFETY: committed scene, valid ray/hit and context.
            unsafe { rtcIntersect1(self.scene, &mut ctx, &mut rh) };
            (rh.hit.geom_id != INVALID_ID).then_some((rh.ray.tfar, rh.hit.prim_id))
        }

        /// Any hit (occlusion).
        pub fn occluded(&self, org: [f32; 3], dir: [f32; 3], tnear: f32, tfar: f32) -> bool {
            let mut r = RtcRay { org, tnear, dir, time: 0.0, tfar, mask: u32::MAX, id: 0, flags: 0 };
            let mut ctx = context();
            // SAFETY: as above.
            unsafe { rtcOccluded1(self.scene, &mut ctx, &mut r) };
            r.tfar == f32::NEG_INFINITY
        }
    }

    impl Drop for Scene {
        fn drop(&mut self) {
            // SAFETY: created by rtcNewScene, released once.
            unsafe { rtcReleaseScene(self.scene) };
        }
    }

    /// Node of the tree Embree builds through our callbacks (in Embree's thread-local memory).
    #[repr(C)]
    struct Node {
        /// 0 = inner, else primitive count of a leaf.
        leaf_count: u32,
        children: [*mut Node; 2],
        bounds: [Bounds; 2],
    }

    unsafe extern "C" fn create_node(alloc: *mut c_void, child_count: c_uint, _user: *mut c_void) -> *mut c_void {
        assert!(child_count == 2);
        // SAFETY: Embree's allocator returns memory valid until the BVH is released.
        let n = unsafe { rtcThreadLocalAlloc(alloc, std::mem::size_of::<Node>(), 16) } as *mut Node;
        // SAFETY: n is fresh, aligned and large enough.
        unsafe { n.write(Node { leaf_count: 0, children: [std::ptr::null_mut(); 2], bounds: [[0.0; 6]; 2] }) };
        n as *mut c_void
    }

    unsafe extern "C" fn set_children(node: *mut c_void, children: *mut *mut c_void, count: c_uint, _user: *mut c_void) {
        let n = node as *mut Node;
        for i in 0..count as usize {
            // SAFETY: Embree passes `count` (= 2) valid child pointers for a node we created.
            unsafe { (*n).children[i] = *children.add(i) as *mut Node };
        }
    }

    unsafe extern "C" fn set_bounds(node: *mut c_void, bounds: *const *const RtcBounds, count: c_uint, _user: *mut c_void) {
        let n = node as *mut Node;
        for i in 0..count as usize {
            // SAFETY: as above, `count` bounds pointers.
            let b = unsafe { &**bounds.add(i) };
            // SAFETY: n is a node we created.
            unsafe { (*n).bounds[i] = [b.lower[0], b.lower[1], b.lower[2], b.upper[0], b.upper[1], b.upper[2]] };
        }
    }

    unsafe extern "C" fn create_leaf(alloc: *mut c_void, _prims: *const BuildPrimitive, count: usize, _user: *mut c_void) -> *mut c_void {
        // SAFETY: as in create_node.
        let n = unsafe { rtcThreadLocalAlloc(alloc, std::mem::size_of::<Node>(), 16) } as *mut Node;
        // SAFETY: fresh memory.
        unsafe { n.write(Node { leaf_count: count as u32, children: [std::ptr::null_mut(); 2], bounds: [[0.0; 6]; 2] }) };
        n as *mut c_void
    }

    /// Spatial split of a triangle's reference (HIGH quality): clip the triangle's polygon at
    /// `pos` along `dim` and bound each side, within the reference's current box.
    unsafe extern "C" fn split_primitive(prim: *const BuildPrimitive, dim: c_uint, pos: f32, left: *mut RtcBounds, right: *mut RtcBounds, user: *mut c_void) {
        // SAFETY: user is the &Mesh we passed; prim is valid for the call.
        let (mesh, p) = unsafe { (&*(user as *const Mesh), &*prim) };
        let d = dim as usize;
        let tri = mesh.triangle(p.prim_id as usize);
        let mut lb = [f32::INFINITY, f32::INFINITY, f32::INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY];
        let mut rb = lb;
        let grow = |b: &mut Bounds, v: [f32; 3]| {
            for k in 0..3 {
                b[k] = b[k].min(v[k]);
                b[k + 3] = b[k + 3].max(v[k]);
            }
        };
        for i in 0..3 {
            let (a, b) = (tri[i], tri[(i + 1) % 3]);
            if a[d] <= pos {
                grow(&mut lb, a);
            }
            if a[d] >= pos {
                grow(&mut rb, a);
            }
            if (a[d] < pos && b[d] > pos) || (a[d] > pos && b[d] < pos) {
                let t = (pos - a[d]) / (b[d] - a[d]);
                let mut x = [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), a[2] + t * (b[2] - a[2])];
                x[d] = pos;
                grow(&mut lb, x);
                grow(&mut rb, x);
            }
        }
        let clip = |b: Bounds| -> RtcBounds {
            let mut lo = [0f32; 3];
            let mut hi = [0f32; 3];
            for k in 0..3 {
                lo[k] = b[k].max(p.lower[k]);
                hi[k] = b[k + 3].min(p.upper[k]);
            }
            RtcBounds { lower: lo, align0: 0.0, upper: hi, align1: 0.0 }
        };
        let mut l = clip(lb);
        let mut r = clip(rb);
        l.upper[d] = l.upper[d].min(pos);
        r.lower[d] = r.lower[d].max(pos);
        // SAFETY: Embree passes writable bounds.
        unsafe {
            *left = l;
            *right = r;
        }
    }

    /// Binary SAH (PEERS.md) of the tree under `root`, whose own box is `root_box`.
    fn sah(root: *const Node, root_box: &Bounds) -> f64 {
        let ra = area(root_box);
        let mut sum = 0.0;
        let mut stack = vec![(root, *root_box)];
        while let Some((n, b)) = stack.pop() {
            // SAFETY: the tree is alive while the BVH is not released.
            let node = unsafe { &*n };
            if node.leaf_count > 0 {
                sum += area(&b) * node.leaf_count as f64;
            } else {
                sum += area(&b);
                for i in 0..2 {
                    stack.push((node.children[i] as *const Node, node.bounds[i]));
                }
            }
        }
        sum / ra
    }

    pub struct Device(*mut c_void);

    // SAFETY: an Embree device may be used from any thread.
    unsafe impl Send for Device {}

    impl Device {
        pub fn new(threads: usize) -> Self {
            let cfg = CString::new(format!("threads={threads},set_affinity=0")).unwrap();
            // SAFETY: valid NUL-terminated config string.
            let d = unsafe { rtcNewDevice(cfg.as_ptr()) };
            assert!(!d.is_null(), "rtcNewDevice failed");
            Device(d)
        }

        /// Builds with quality 0 LOW, 1 MEDIUM, 2 HIGH; `prims` is consumed (Embree reorders
        /// and, for HIGH, appends split references up to its capacity).
        pub fn build(&self, quality: u32, mesh: &Mesh, prims: &mut [BuildPrimitive], count: usize) -> Built {
            // SAFETY: device is valid.
            let bvh = unsafe { rtcNewBVH(self.0) };
            let args = BuildArguments {
                byte_size: std::mem::size_of::<BuildArguments>(),
                build_quality: quality,
                build_flags: 0,
                max_branching_factor: 2,
                max_depth: 1024,
                sah_block_size: 1,
                min_leaf_size: 1,
                max_leaf_size: 8,
                traversal_cost: 1.0,
                intersection_cost: 1.0,
                bvh,
                primitives: prims.as_mut_ptr(),
                primitive_count: count,
                primitive_array_capacity: prims.len(),
                create_node: Some(create_node),
                set_node_children: Some(set_children),
                set_node_bounds: Some(set_bounds),
                create_leaf: Some(create_leaf),
                split_primitive: Some(split_primitive),
                build_progress: std::ptr::null_mut(),
                user_ptr: mesh as *const Mesh as *mut c_void,
            };
            // SAFETY: args follow rtcore_builder.h; prims has `capacity` elements, 32-B aligned.
            let root = unsafe { rtcBuildBVH(&args) } as *const Node;
            // SAFETY: device is valid.
            let err = unsafe { rtcGetDeviceError(self.0) };
            assert!(!root.is_null() && err == 0, "rtcBuildBVH failed (error {err})");
            // Root box: the builder gives only child boxes.
            // SAFETY: root is a node of the live BVH.
            let r = unsafe { &*root };
            let root_box = if r.leaf_count > 0 {
                prims[..count].iter().fold([f32::INFINITY, f32::INFINITY, f32::INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY], |b, p| {
                    super::union(&b, &[p.lower[0], p.lower[1], p.lower[2], p.upper[0], p.upper[1], p.upper[2]])
                })
            } else {
                super::union(&r.bounds[0], &r.bounds[1])
            };
            Built { bvh, root, root_box }
        }
    }

    /// A built Embree BVH (released on drop).
    pub struct Built {
        bvh: *mut c_void,
        root: *const Node,
        root_box: Bounds,
    }

    impl Built {
        pub fn sah(&self) -> f64 {
            sah(self.root, &self.root_box)
        }
    }

    impl Drop for Built {
        fn drop(&mut self) {
            // SAFETY: releasing the BVH frees the nodes; nothing refers to them afterwards.
            unsafe { rtcReleaseBVH(self.bvh) };
        }
    }

    impl Drop for Device {
        fn drop(&mut self) {
            // SAFETY: the device was created by rtcNewDevice and is released once.
            unsafe { rtcReleaseDevice(self.0) };
        }
    }

    /// Build primitives of a mesh (capacity 2N for HIGH's spatial splits).
    pub fn primitives(mesh: &Mesh, capacity: usize) -> Vec<BuildPrimitive> {
        let mut v = vec![BuildPrimitive::default(); capacity.max(mesh.indices.len())];
        for (i, slot) in v.iter_mut().enumerate().take(mesh.indices.len()) {
            let b = super::triangle_bounds(mesh, i);
            *slot = BuildPrimitive { lower: [b[0], b[1], b[2]], geom_id: 0, upper: [b[3], b[4], b[5]], prim_id: i as u32 };
        }
        v
    }
}

pub mod obvhs_peer {
    //! obvhs 0.3.3 PLOC (fastest_build preset, as in PEERS.md) and its SAH by our formula.
    use super::area;
    use arbor_scene::Mesh;
    use obvhs::{bvh2::builder::build_bvh2_from_tris, triangle::Triangle, BvhBuildParams};
    use obvhs_glam::Vec3A;

    pub fn triangles(mesh: &Mesh) -> Vec<Triangle> {
        (0..mesh.indices.len())
            .map(|i| {
                let [a, b, c] = mesh.triangle(i);
                Triangle { v0: Vec3A::from_array(a), v1: Vec3A::from_array(b), v2: Vec3A::from_array(c) }
            })
            .collect()
    }

    pub fn build(tris: &[Triangle]) -> obvhs::bvh2::Bvh2 {
        let mut t = std::time::Duration::ZERO;
        build_bvh2_from_tris(tris, BvhBuildParams::fastest_build(), &mut t)
    }

    pub fn sah(bvh: &obvhs::bvh2::Bvh2) -> f64 {
        let b = |i: usize| {
            let a = &bvh.nodes[i].aabb;
            [a.min.x, a.min.y, a.min.z, a.max.x, a.max.y, a.max.z]
        };
        let root = area(&b(0));
        let mut sum = 0.0;
        let mut stack = vec![0usize];
        while let Some(i) = stack.pop() {
            let n = &bvh.nodes[i];
            if n.prim_count > 0 {
                sum += area(&b(i)) * n.prim_count as f64;
            } else {
                sum += area(&b(i));
                stack.push(n.first_index as usize);
                stack.push(n.first_index as usize + 1);
            }
        }
        sum / root
    }
}
