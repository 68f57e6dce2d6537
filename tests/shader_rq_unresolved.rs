//! A TLAS instance whose BLAS is gone (destroyed, or never built at that address) in the
//! shader library: traversal treats the instance as absent — every ray finds exactly what a
//! TLAS without that instance gives — and the dispatch reports the reference once
//! (`DispatchReport::unresolved_instance`), not once per ray and not as a memory fault. And an
//! array of acceleration-structure descriptors, each element its own TLAS.
mod reference;

use std::path::PathBuf;

use arbor::accel::{AsType, Geometry, GeometryData, GeometryFlags, MapView};
use arbor::shader::{dispatch, FaultKind, FaultSpace, HostMemory, Memory, Module, Pipeline, Watchdog};
use arbor_scene::{InstanceRecord, Mesh};
use reference::*;

const QUAD: u64 = 0x20_0000_0000;
const MISSING: u64 = 0x21_0000_0000;
const TLAS: u64 = 0x7F_0000_0000;

fn rq_negative() -> Vec<u32> {
    compile("rq_negative.comp")
}

fn compile(name: &str) -> Vec<u32> {
    let src = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/shaders").join(name);
    let out = std::env::temp_dir().join(format!("arbor-rq-unresolved-{}-{name}.spv", std::process::id()));
    let r = std::process::Command::new("glslangValidator").args(["-V", "--target-env", "vulkan1.2", "-o"]).arg(&out).arg(&src).output().expect("glslangValidator");
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stdout));
    std::fs::read(&out).unwrap().chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect()
}

fn quad_blas() -> Vec<u8> {
    let m = Mesh { positions: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]], indices: vec![[0, 1, 2], [0, 2, 3]] };
    build_blas(0, &[TriData::from_mesh(&m, 0).geometry()]).bytes
}

/// A TLAS over instances of the given references (identity transforms, all rays' paths), built
/// while every reference is a live BLAS.
fn tlas(references: &[u64]) -> Vec<u8> {
    tlas_at(references, 0.0)
}

/// `tlas` with every instance moved by `x` along x.
fn tlas_at(references: &[u64], x: f32) -> Vec<u8> {
    let mut view = MapView::new();
    for &r in references {
        view.insert(r, quad_blas());
    }
    let instances: Vec<InstanceRecord> = references
        .iter()
        .map(|&reference| {
            let mut transform = InstanceRecord::IDENTITY;
            transform[3] = x;
            InstanceRecord { transform, custom_index: 0, mask: 0xFF, sbt_offset: 0, flags: 0, reference }
        })
        .collect();
    let packed = InstanceRecord::pack(&instances);
    let g = [Geometry { flags: GeometryFlags(0), primitive_count: instances.len() as u32, data: GeometryData::Instances { array_of_pointers: false, data: &packed } }];
    build(AsType::TopLevel, 0, &g, &view).bytes
}

/// Runs rq_negative (8 invocations a workgroup) on the TLAS in `view`; the report and the
/// output words.
fn run(p: &Pipeline, view: MapView, groups: u32) -> (arbor::shader::DispatchReport, Vec<u8>) {
    struct Mem(HostMemory, MapView);
    impl Memory for Mem {
        fn binding(&self, s: u32, b: u32) -> Option<arbor::shader::Region> {
            self.0.binding(s, b)
        }
        fn address(&self, a: u64, l: u64) -> Option<arbor::shader::Region> {
            self.0.address(a, l)
        }
        fn read(&self, b: u64, o: u64, out: &mut [u8]) -> bool {
            self.0.read(b, o, out)
        }
        fn write(&self, b: u64, o: u64, d: &[u8]) -> bool {
            self.0.write(b, o, d)
        }
        fn atomic(&self, b: u64, o: u64, s: usize, u: &dyn Fn(u64) -> u64) -> Option<u64> {
            self.0.atomic(b, o, s, u)
        }
        fn acceleration_structures(&self) -> Option<&dyn arbor::accel::DeviceView> {
            Some(&self.1)
        }
    }
    let mut host = HostMemory::new();
    let out = host.add_buffer(&vec![0xEE; 128 * groups as usize]);
    host.bind(0, 0, out);
    let mem = Mem(host, view);
    let report = dispatch(p, &mem, &TLAS.to_le_bytes(), [groups, 1, 1], [0; 3], &Watchdog::default());
    (report, mem.0.bytes(out))
}

#[test]
fn an_instance_without_its_blas_is_absent_and_reported_once_per_dispatch() {
    let words = rq_negative();
    let p = Pipeline::compute(&Module::parse(&words).unwrap(), "main", &[]).unwrap();
    // The instance of MISSING comes first and second, so every ray meets it.
    let mut view = MapView::new();
    view.insert(QUAD, quad_blas());
    view.insert(TLAS, tlas(&[MISSING, QUAD, MISSING]));
    let (report, got) = run(&p, view, 4);
    // The reference: the same rays through a TLAS that only has the live instance.
    let mut only = MapView::new();
    only.insert(QUAD, quad_blas());
    only.insert(TLAS, tlas(&[QUAD]));
    let (clean, want) = run(&p, only, 4);
    assert!(clean.is_clean(), "{clean:?}");
    assert_eq!(got, want, "the unresolved instances are absent; the live one is hit as without them");
    assert_eq!(report.fault_count, 0, "not a memory fault: {report:?}");
    let f = report.unresolved_instance.expect("the unresolved reference is reported");
    assert_eq!((f.kind, f.space, f.at), (FaultKind::UnresolvedInstance, FaultSpace::RayQuery, MISSING));
    assert_eq!(f.workgroup, [0, 0, 0], "the first workgroup in order names it");
    assert!(!report.is_clean());
}

#[test]
fn an_array_of_structures_traces_the_element_the_index_names() {
    const TLAS1: u64 = 0x7E_0000_0000;
    struct Mem(HostMemory, MapView);
    impl Memory for Mem {
        fn binding(&self, s: u32, b: u32) -> Option<arbor::shader::Region> {
            self.0.binding(s, b)
        }
        fn address(&self, a: u64, l: u64) -> Option<arbor::shader::Region> {
            self.0.address(a, l)
        }
        fn read(&self, b: u64, o: u64, out: &mut [u8]) -> bool {
            self.0.read(b, o, out)
        }
        fn write(&self, b: u64, o: u64, d: &[u8]) -> bool {
            self.0.write(b, o, d)
        }
        fn atomic(&self, b: u64, o: u64, s: usize, u: &dyn Fn(u64) -> u64) -> Option<u64> {
            self.0.atomic(b, o, s, u)
        }
        fn acceleration_structure_element(&self, set: u32, binding: u32, element: u32) -> Option<u64> {
            ((set, binding) == (0, 1)).then(|| [TLAS, TLAS1].get(element as usize).copied()).flatten()
        }
        fn acceleration_structures(&self) -> Option<&dyn arbor::accel::DeviceView> {
            Some(&self.1)
        }
    }
    let p = Pipeline::compute(&Module::parse(&compile("rq_array.comp")).unwrap(), "main", &[]).unwrap();
    assert_eq!(p.bindings().iter().find(|b| b.binding == 1).map(|b| b.count), Some(2), "the array's length is what the layout is checked against");
    // Element 0: the quad under x = 0.5; element 1: under x = 5.5.
    let mut view = MapView::new();
    view.insert(QUAD, quad_blas());
    view.insert(TLAS, tlas_at(&[QUAD], 0.0));
    view.insert(TLAS1, tlas_at(&[QUAD], 5.0));
    let mut host = HostMemory::new();
    let out = host.add_buffer(&[0xEE; 32]);
    host.bind(0, 0, out);
    let mem = Mem(host, view);
    for pick in 0..2u32 {
        let report = dispatch(&p, &mem, &pick.to_le_bytes(), [1, 1, 1], [0; 3], &Watchdog::default());
        assert!(report.is_clean(), "{report:?}");
        let got: Vec<u32> = mem.0.bytes(out).chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect();
        // Lane i traces at x = 0.5 (even) or 5.5 (odd): a triangle hit (1) where the picked element has its quad.
        let want: Vec<u32> = (0..8).map(|i| u32::from(i % 2 == pick)).collect();
        assert_eq!(got, want, "element {pick}");
    }
    // An index past the array is a fault naming the element; the query finds nothing.
    let report = dispatch(&p, &mem, &5u32.to_le_bytes(), [1, 1, 1], [0; 3], &Watchdog::default());
    assert!(report.faults.iter().any(|f| f.kind == FaultKind::ArrayIndex && f.space == FaultSpace::ArrayElement { set: 0, binding: 1, element: 5 }), "{report:?}");
}
