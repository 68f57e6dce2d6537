//! The SIMD-lane executor and `dispatch`.
//!
//! A workgroup is split into lane groups of [`LANES`] invocations. A lane group runs one block
//! at a time for the lanes whose cursor is the lowest block index among its running lanes (the
//! execution mask); every op loops over all lanes and blends its result under the mask, so op
//! bodies are short fixed-length loops. Because blocks are in structured order, lanes that
//! diverged meet again at the merge block before it runs. A lane group's state is plain data,
//! so a workgroup barrier is: run every group until its lanes wait at the barrier (or exit),
//! then release them all. Workgroups of a dispatch run in parallel on rayon; each writes only
//! through [`Memory`], and faults are collected per workgroup in index order, so the report
//! does not depend on thread timing.
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

use rayon::prelude::*;

use super::alu;
use super::exec_alu::{exec_bin, exec_tri, exec_un, map1, map2, map3};
use super::ir::{builtin_offset as bo, BallotOp, BinOp, Block, Op, Program, Sc, SgOp, Space, Term};
use super::memory::{Fault, ImageBinding, Memory, Region};
use super::{Pipeline, LANES};

/// Faults kept in a report; later ones are only counted.
const MAX_FAULTS: usize = 16;
/// How many blocks a lane group runs between watchdog checks.
pub(super) const CHECK_EVERY: u64 = 1024;

/// Stops a dispatch that runs too long. All fields optional; `Default` never stops.
#[derive(Clone, Debug, Default)]
pub struct Watchdog<'f> {
    /// Stop once this instant has passed (the runtime's per-submission deadline).
    pub deadline: Option<Instant>,
    /// Stop when this flag becomes true (device lost, process shutting down).
    pub cancel: Option<Arc<AtomicBool>>,
    /// Stop when any of these becomes true: flags the caller owns and cannot share as an
    /// `Arc` (a queue's stop flag, a device's lost flag).
    pub stop_flags: &'f [&'f AtomicBool],
    /// Stop a workgroup after this many block executions of one lane group.
    pub step_budget: Option<u64>,
}

/// Why a dispatch stopped early.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stop {
    Deadline,
    Cancelled,
    StepBudget,
}

/// What a dispatch did: contained faults (the first few, in workgroup order, and how many) and
/// whether the watchdog stopped it. Memory written before a stop stays written.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DispatchReport {
    pub faults: Vec<Fault>,
    pub fault_count: u64,
    pub stopped: Option<Stop>,
    /// The first TLAS instance reference (in workgroup order) that named no built BLAS
    /// ([`super::FaultKind::UnresolvedInstance`]), kept apart from `faults`: it is reported
    /// once per dispatch however many rays met it.
    pub unresolved_instance: Option<Fault>,
}

impl DispatchReport {
    pub fn is_clean(&self) -> bool {
        self.fault_count == 0 && self.stopped.is_none() && self.unresolved_instance.is_none()
    }
}

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Lane {
    Running,
    AtBarrier,
    Done,
}

pub(super) type Regs = [u64; LANES];

/// One lane group: registers, cursors, per-lane memory and ray queries — plain data (the
/// queries borrow structure bytes from the dispatch's memory, `'a`).
pub(super) struct Group<'a> {
    /// Index of this lane group in its workgroup (first invocation = index * LANES).
    pub index: u32,
    pub regs: Vec<Regs>,
    cursor: [u32; LANES],
    lane: [Lane; LANES],
    pub frame: Vec<u8>,
    pub queries: super::exec_rq::Queries<'a>,
}

/// Per-dispatch, read-only context.
pub(super) struct Ctx<'a> {
    pub prog: &'a Program,
    pub mem: &'a dyn Memory,
    /// Per `Program::bindings` slot, the region of each array element (one for a single
    /// descriptor).
    pub regions: Vec<Vec<Option<Region>>>,
    /// Per `Program::bindings` slot, where native code loads and stores inline: the host
    /// address and length of a single descriptor's region (`Memory::host_span`), or [0, 0].
    pub spans: Vec<[u64; 2]>,
    /// Per `Program::images` slot, the view of each array element (one for a single image).
    pub images: Vec<Vec<Option<ImageBinding>>>,
    pub push: &'a [u8],
    /// Device addresses of `Program::accel_bindings` (0 when nothing is bound).
    accel: Vec<u64>,
    /// Per `Program::accel_arrays` slot, each element's structure address (0 when unbound).
    pub accel_arrays: Vec<Vec<u64>>,
    pub local: [u32; 3],
    num_groups: [u32; 3],
    pub watchdog: &'a Watchdog<'a>,
    stop: AtomicBool,
    /// What of a lane frame the program reads (`frame_use`).
    frame: FrameUse,
}

/// Per-workgroup mutable state besides the lane groups.
pub(super) struct Wg {
    pub id: [u32; 3],
    pub shared: Vec<u8>,
    pub faults: Vec<Fault>,
    pub fault_count: u64,
    /// The first unresolved instance reference a ray query of this workgroup met.
    pub unresolved: Option<Fault>,
    pub steps: u64,
    pub stopped: Option<Stop>,
}

/// What one workgroup leaves for the report: its first faults, their count, a watchdog stop,
/// and the first unresolved instance reference its ray queries met.
type WorkgroupResult = (Vec<Fault>, u64, Option<Stop>, Option<Fault>);

/// Runs `group_count` workgroups starting at `base_group` (vkCmdDispatchBase). Never panics on
/// shader behaviour: bad accesses become faults, endless loops meet the watchdog.
pub fn dispatch(
    pipeline: &Pipeline,
    memory: &dyn Memory,
    push_constants: &[u8],
    group_count: [u32; 3],
    base_group: [u32; 3],
    watchdog: &Watchdog,
) -> DispatchReport {
    let prog = &*pipeline.program;
    // Push-constant bytes the program reads but the caller left out read as zero, as the
    // runtime pads them: loads of them may run speculatively (`lower_select`).
    let padded: Vec<u8>;
    let push_constants = if push_constants.len() < pipeline.push_constant_size as usize {
        padded = push_constants.iter().copied().chain(std::iter::repeat(0)).take(pipeline.push_constant_size as usize).collect();
        &padded[..]
    } else {
        push_constants
    };
    let regions = super::exec_mem::binding_regions(prog, memory);
    let ctx = Ctx {
        prog,
        mem: memory,
        spans: super::exec_mem::host_spans(prog, memory, &regions),
        regions,
        images: super::exec_image::image_bindings(prog, memory),
        push: push_constants,
        accel: prog.accel_bindings.iter().map(|&(_, (s, b))| memory.acceleration_structure(s, b).unwrap_or(0)).collect(),
        accel_arrays: super::exec_mem::accel_arrays(prog, memory),
        local: pipeline.local_size,
        // NumWorkgroups is the dispatch's group count, base or not (vkCmdDispatchBase).
        num_groups: group_count,
        watchdog,
        stop: AtomicBool::new(false),
        frame: frame_use(prog),
    };
    let total = group_count.iter().map(|&c| c as u64).product::<u64>();
    let per_row = group_count[0] as u64 * group_count[1] as u64;
    let id_of = |i: u64| {
        [
            base_group[0].wrapping_add((i % group_count[0] as u64) as u32),
            base_group[1].wrapping_add(((i / group_count[0] as u64) % group_count[1] as u64) as u32),
            base_group[2].wrapping_add((i / per_row) as u32),
        ]
    };
    let keep = |r: &WorkgroupResult| r.1 > 0 || r.2.is_some() || r.3.is_some();
    // The backend was chosen at pipeline creation: native code when the program compiled.
    let results: Vec<WorkgroupResult> = match &pipeline.jit {
        Some(jit) => (0..total)
            .into_par_iter()
            .map_init(|| vec![0u8; prog.lane_frame.len() * jit.lanes], |frame, i| run_workgroup_jit(&ctx, jit, frame, id_of(i)))
            .filter(keep)
            .collect(),
        None => (0..total).into_par_iter().map_init(|| new_groups(&ctx), |groups, i| run_workgroup(&ctx, groups, id_of(i))).filter(keep).collect(),
    };
    let mut report = DispatchReport::default();
    for (faults, count, stop, unresolved) in results {
        report.unresolved_instance = report.unresolved_instance.or(unresolved);
        report.fault_count += count;
        report.faults.extend(faults.into_iter().take(MAX_FAULTS - report.faults.len().min(MAX_FAULTS)));
        report.stopped = report.stopped.or(stop);
    }
    report
}

fn new_groups<'a>(ctx: &Ctx<'a>) -> Vec<Group<'a>> {
    let n = ctx.local.iter().product::<u32>() as usize;
    let frame = ctx.prog.lane_frame.len();
    (0..n.div_ceil(LANES))
        .enumerate()
        .map(|(index, _)| Group {
            index: index as u32,
            regs: vec![[0; LANES]; ctx.prog.reg_count as usize],
            cursor: [0; LANES],
            lane: [Lane::Done; LANES],
            frame: vec![0; frame * LANES],
            queries: super::exec_rq::Queries::new(),
        })
        .collect()
}

impl Wg {
    fn new(ctx: &Ctx, id: [u32; 3]) -> Wg {
        Wg { id, shared: vec![0; ctx.prog.workgroup_bytes as usize], faults: Vec::new(), fault_count: 0, unresolved: None, steps: 0, stopped: None }
    }
}

fn run_workgroup_jit(ctx: &Ctx, jit: &super::jit::Jit, frame: &mut [u8], id: [u32; 3]) -> WorkgroupResult {
    if ctx.stop.load(Ordering::Relaxed) {
        return (Vec::new(), 0, None, None);
    }
    let mut wg = Wg::new(ctx, id);
    super::jit::run_workgroup(ctx, jit, &mut wg, frame);
    if wg.stopped.is_some() {
        ctx.stop.store(true, Ordering::Relaxed);
    }
    (wg.faults, wg.fault_count, wg.stopped, wg.unresolved)
}

fn run_workgroup<'a>(ctx: &Ctx<'a>, groups: &mut [Group<'a>], id: [u32; 3]) -> WorkgroupResult {
    if ctx.stop.load(Ordering::Relaxed) {
        return (Vec::new(), 0, None, None);
    }
    let mut wg = Wg::new(ctx, id);
    let n = ctx.local.iter().product::<u32>();
    for (g, group) in groups.iter_mut().enumerate() {
        init_group(ctx, group, &wg, g as u32, n);
    }
    loop {
        for group in groups.iter_mut() {
            run_group(ctx, group, &mut wg);
            if wg.stopped.is_some() {
                ctx.stop.store(true, Ordering::Relaxed);
                return (wg.faults, wg.fault_count, wg.stopped, wg.unresolved);
            }
        }
        // Every group now waits at the barrier or is done: release the barrier.
        let mut waiting = false;
        for group in groups.iter_mut() {
            for l in group.lane.iter_mut().filter(|l| **l == Lane::AtBarrier) {
                *l = Lane::Running;
                waiting = true;
            }
        }
        if !waiting {
            return (wg.faults, wg.fault_count, None, wg.unresolved);
        }
    }
}

fn init_group(ctx: &Ctx, group: &mut Group, wg: &Wg, g: u32, n: u32) {
    let prog = ctx.prog;
    for &(r, v) in &prog.consts {
        group.regs[r as usize] = [v; LANES];
    }
    for (&(r, _), &address) in prog.accel_bindings.iter().zip(&ctx.accel) {
        group.regs[r as usize] = [address; LANES];
    }
    group.queries.clear();
    let fs = prog.lane_frame.len();
    for l in 0..LANES {
        let index = g * LANES as u32 + l as u32;
        group.cursor[l] = 0;
        group.lane[l] = if index < n { Lane::Running } else { Lane::Done };
        init_frame(ctx, &mut group.frame[l * fs..(l + 1) * fs], wg.id, index, n);
    }
}

/// What of a lane frame a program reads: a bit per word of the built-in area, and whether
/// anything past it (Private and Function variables, whose initial contents each invocation
/// must then find).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct FrameUse {
    pub builtins: u64,
    pub tail: bool,
}

/// Lane-frame accesses at constant offsets name the words they reach; one at a computed offset
/// may reach any.
pub(super) fn frame_use(prog: &Program) -> FrameUse {
    let words = bo::END / 4;
    let mut konst = vec![None; prog.reg_count as usize];
    prog.consts.iter().for_each(|&(r, k)| konst[r as usize] = Some(k));
    let mut written = vec![false; prog.reg_count as usize];
    for b in &prog.blocks {
        b.ops.iter().flat_map(Op::defs).chain(b.phi_in.iter().map(|p| p.0)).chain(b.edge_moves.iter().map(|m| m.dst)).for_each(|r| written[r as usize] = true);
    }
    let mut used = FrameUse { builtins: 0, tail: false };
    for op in prog.blocks.iter().flat_map(|b| &b.ops) {
        let (ty, addr) = match *op {
            Op::Load { ty, space: Space::Lane, addr, .. } | Op::Store { ty, space: Space::Lane, addr, .. } | Op::Atomic { ty, space: Space::Lane, addr, .. } => (ty, addr),
            _ => continue,
        };
        match konst[addr as usize].filter(|_| !written[addr as usize]) {
            Some(k) if k >= bo::END as u64 => used.tail = true,
            Some(k) => (k / 4..(k + ty.size() as u64).div_ceil(4).min(words as u64)).for_each(|w| used.builtins |= 1 << w),
            None => return FrameUse { builtins: (1 << words) - 1, tail: true },
        }
    }
    used
}

/// Fills invocation `index`'s lane frame (of `n` in workgroup `id`): the built-in words the
/// program reads, then the program's initial contents past them when it reads those.
pub(super) fn init_frame(ctx: &Ctx, frame: &mut [u8], id: [u32; 3], index: u32, n: u32) {
    let [lx, ly, lz] = ctx.local;
    // A one-dimensional workgroup (the common shape) needs no division.
    let local = if ly == 1 && lz == 1 { [index, 0, 0] } else { [index % lx, (index / lx) % ly, index / (lx * ly)] };
    let end = (bo::END as usize).min(frame.len());
    let (head, tail) = frame.split_at_mut(end);
    let mut words = ctx.frame.builtins;
    while words != 0 {
        let w = words.trailing_zeros();
        words &= words - 1;
        if let Some(d) = head.get_mut(4 * w as usize..4 * w as usize + 4) {
            d.copy_from_slice(&builtin_word(ctx, id, index, n, local, w).to_le_bytes());
        }
    }
    if let Some(init) = ctx.prog.lane_frame.get(end..).filter(|t| ctx.frame.tail && t.len() == tail.len()) {
        tail.copy_from_slice(init);
    }
}

/// Word `w` of the built-in area (`ir::builtin_offset`) of invocation `index` (of `n`, local id
/// `local`) in workgroup `id`. A subgroup mask's upper words are zero.
fn builtin_word(ctx: &Ctx, id: [u32; 3], index: u32, n: u32, local: [u32; 3], w: u32) -> u32 {
    // Word indices: range patterns over them compile to one table jump.
    const GID: u32 = bo::GLOBAL_INVOCATION_ID / 4;
    const LID: u32 = bo::LOCAL_INVOCATION_ID / 4;
    const WID: u32 = bo::WORKGROUP_ID / 4;
    const NWG: u32 = bo::NUM_WORKGROUPS / 4;
    const IDX: u32 = bo::LOCAL_INVOCATION_INDEX / 4;
    const WGS: u32 = bo::WORKGROUP_SIZE / 4;
    const SGS: u32 = bo::SUBGROUP_SIZE / 4;
    const SLI: u32 = bo::SUBGROUP_LOCAL_INVOCATION_ID / 4;
    const SID: u32 = bo::SUBGROUP_ID / 4;
    const NSG: u32 = bo::NUM_SUBGROUPS / 4;
    const EQ: u32 = bo::SUBGROUP_EQ_MASK / 4;
    const GE: u32 = bo::SUBGROUP_GE_MASK / 4;
    const GT: u32 = bo::SUBGROUP_GT_MASK / 4;
    const LE: u32 = bo::SUBGROUP_LE_MASK / 4;
    const LT: u32 = bo::SUBGROUP_LT_MASK / 4;
    let lane = index % LANES as u32;
    let all = (1u32 << LANES) - 1;
    match w {
        GID..LID => id[(w - GID) as usize].wrapping_mul(ctx.local[(w - GID) as usize]).wrapping_add(local[(w - GID) as usize]),
        LID..WID => local[(w - LID) as usize],
        WID..NWG => id[(w - WID) as usize],
        NWG..IDX => ctx.num_groups[(w - NWG) as usize],
        IDX => index,
        WGS..SGS => ctx.local[(w - WGS) as usize],
        SGS => LANES as u32,
        SLI => lane,
        SID => index / LANES as u32,
        NSG => n.div_ceil(LANES as u32),
        EQ => 1 << lane,
        GE => all & !((1 << lane) - 1),
        GT => all & !((2 << lane) - 1),
        LE => (2 << lane) - 1,
        LT => (1 << lane) - 1,
        _ => 0,
    }
}

/// Runs a lane group until none of its lanes is running (all done or at a barrier).
///
/// Finding the lowest cursor is a pass over the lanes; it is needed only when lanes that ran
/// apart may meet. While the lanes of the mask go on to a block below every other running
/// lane's cursor (a uniform branch, a loop whose lanes keep going together, the lower side of
/// a split), `exec_block` names the next block and mask itself.
fn run_group<'a>(ctx: &Ctx<'a>, group: &mut Group<'a>, wg: &mut Wg) {
    loop {
        // The lowest cursor among running lanes, which lanes are there, and the lowest cursor
        // of the others (branch-free passes over the lanes: the cursors of lanes not running
        // read as u32::MAX).
        let key: [u32; LANES] = std::array::from_fn(|l| if group.lane[l] == Lane::Running { group.cursor[l] } else { u32::MAX });
        let min = key.iter().fold(u32::MAX, |m, &k| m.min(k));
        if min == u32::MAX {
            return;
        }
        let mut mask = 0u32;
        let mut rest = u32::MAX;
        for (l, &k) in key.iter().enumerate() {
            mask |= ((k == min) as u32) << l;
            rest = rest.min(if k == min { u32::MAX } else { k });
        }
        let mut next = Some(Next { block: min, mask, rest });
        while let Some(n) = next {
            wg.steps += 1;
            if wg.steps.is_multiple_of(CHECK_EVERY) {
                if let Some(stop) = check_watchdog(ctx.watchdog, wg.steps) {
                    wg.stopped = Some(stop);
                    return;
                }
            }
            next = exec_block(ctx, group, wg, n);
        }
    }
}

/// A block to run, the lanes that run it, and the lowest cursor of the other running lanes
/// (`block` is below it).
#[derive(Clone, Copy)]
struct Next {
    block: u32,
    mask: u32,
    rest: u32,
}

impl Next {
    /// The step after lanes `lo` go to block `a` and lanes `hi` to block `b` (either mask may
    /// be empty), when that is one of the two blocks and below every other cursor.
    fn after(a: u32, lo: u32, b: u32, hi: u32, rest: u32) -> Option<Next> {
        let (a, lo, b, hi) = if lo == 0 || (hi != 0 && b < a) { (b, hi, a, lo) } else { (a, lo, b, hi) };
        let rest = if hi != 0 { rest.min(b) } else { rest };
        (lo != 0 && a < rest).then_some(Next { block: a, mask: lo, rest })
    }
}

pub(super) fn check_watchdog(w: &Watchdog, steps: u64) -> Option<Stop> {
    if w.step_budget.is_some_and(|b| steps >= b) {
        return Some(Stop::StepBudget);
    }
    if w.cancel.as_ref().is_some_and(|c| c.load(Ordering::Relaxed)) || w.stop_flags.iter().any(|f| f.load(Ordering::Relaxed)) {
        return Some(Stop::Cancelled);
    }
    if w.deadline.is_some_and(|d| Instant::now() >= d) {
        return Some(Stop::Deadline);
    }
    None
}

#[inline(always)]
fn on(mask: u32, l: usize) -> bool {
    (mask >> l) & 1 != 0
}

fn exec_block<'a>(ctx: &Ctx<'a>, group: &mut Group<'a>, wg: &mut Wg, next: Next) -> Option<Next> {
    let Next { block: index, mask, rest } = next;
    let block = &ctx.prog.blocks[index as usize];
    let regs = &mut group.regs;
    for &(dst, tmp) in &block.phi_in {
        let t = regs[tmp as usize];
        let d = &mut regs[dst as usize];
        for l in 0..LANES {
            if on(mask, l) {
                d[l] = t[l];
            }
        }
    }
    for op in &block.ops {
        // The ALU ops, most of what runs, are dispatched here: `exec_op`'s larger frame is
        // paid only by the others.
        match *op {
            Op::Bin { op, ty, dst, a, b } => exec_bin(&mut group.regs, op, ty, dst, mask, a, b),
            Op::Select { dst, cond, a, b } => map3(&mut group.regs, dst, mask, cond, a, b, |c, x, y| if c != 0 { x } else { y }),
            Op::Tri { op, ty, dst, a, b, c } => exec_tri(&mut group.regs, op, ty, dst, mask, a, b, c),
            Op::Un { op, ty, from, dst, a } => exec_un(&mut group.regs, op, ty, from, dst, mask, a),
            _ => exec_op(ctx, group, wg, op, mask),
        }
    }
    // Jumps and two-way branches as masks: each edge's lanes move (and fill its phi
    // temporaries) together.
    let (t, f, to_t) = match block.term {
        Term::Jump(t) => (t, t, mask),
        Term::Cond { cond, t, f } => {
            let v = &group.regs[cond as usize];
            (t, f, (0..LANES).fold(0u32, |m, l| m | (((v[l] != 0) as u32) << l)) & mask)
        }
        _ => {
            per_lane_term(group, block, mask);
            return None;
        }
    };
    let to_f = mask & !to_t;
    for m in &block.edge_moves {
        let lanes = if m.target == t { to_t } else { 0 } | if m.target == f { to_f } else { 0 };
        let s = group.regs[m.src as usize];
        let d = &mut group.regs[m.dst as usize];
        for l in 0..LANES {
            d[l] = if on(lanes, l) { s[l] } else { d[l] };
        }
    }
    for (l, c) in group.cursor.iter_mut().enumerate() {
        *c = if on(to_t, l) { t } else if on(to_f, l) { f } else { *c };
    }
    Next::after(t, to_t, f, to_f, rest)
}

/// Switches, exits and barriers: each lane of the mask on its own.
fn per_lane_term(group: &mut Group, block: &Block, mask: u32) {
    let regs = &mut group.regs;
    for l in (0..LANES).filter(|&l| on(mask, l)) {
        let target = match &block.term {
            Term::Jump(t) => *t,
            Term::Cond { cond, t, f } => {
                if regs[*cond as usize][l] != 0 { *t } else { *f }
            }
            Term::Switch { sel, default, cases } => {
                let v = regs[*sel as usize][l];
                cases.iter().find(|c| c.0 == v).map_or(*default, |c| c.1)
            }
            Term::Exit => {
                group.lane[l] = Lane::Done;
                continue;
            }
            Term::Barrier(next) => {
                group.lane[l] = Lane::AtBarrier;
                group.cursor[l] = *next;
                continue;
            }
        };
        for m in block.edge_moves.iter().filter(|m| m.target == target) {
            regs[m.dst as usize][l] = regs[m.src as usize][l];
        }
        group.cursor[l] = target;
    }
}

/// dst[l] = f(l) for the lanes in the mask; the others keep their value.
#[inline(always)]
fn lanes(regs: &mut [Regs], dst: u32, mask: u32, f: impl Fn(usize) -> u64) {
    let mut v = [0; LANES];
    for (l, o) in v.iter_mut().enumerate() {
        *o = f(l);
    }
    store_lanes(regs, dst, mask, v);
}

/// Per execution mask, each lane's word mask (all ones for a lane in the mask): the blend
/// below is then whole-word and/or over the lane array, with no per-lane bit extraction.
static LANE_MASKS: [Regs; 1 << LANES] = {
    let mut t = [[0; LANES]; 1 << LANES];
    let mut m = 0;
    while m < 1 << LANES {
        let mut l = 0;
        while l < LANES {
            t[m][l] = if (m >> l) & 1 != 0 { u64::MAX } else { 0 };
            l += 1;
        }
        m += 1;
    }
    t
};

/// dst[l] = v[l] for the lanes in the mask: a plain store when every lane is in it (the usual
/// case), else a branch-free blend.
#[inline(always)]
pub(super) fn store_lanes(regs: &mut [Regs], dst: u32, mask: u32, v: Regs) {
    let d = &mut regs[dst as usize];
    if mask == (1 << LANES) - 1 {
        *d = v;
        return;
    }
    let m = &LANE_MASKS[(mask & ((1 << LANES) - 1)) as usize];
    for ((o, &v), &m) in d.iter_mut().zip(&v).zip(m) {
        *o = (v & m) | (*o & !m);
    }
}

fn exec_op<'a>(ctx: &Ctx<'a>, group: &mut Group<'a>, wg: &mut Wg, op: &Op, mask: u32) {
    let regs = &mut group.regs;
    match *op {
        Op::Mov { dst, src } => {
            let s = regs[src as usize];
            store_lanes(regs, dst, mask, s);
        }
        Op::Bin { op, ty, dst, a, b } => exec_bin(regs, op, ty, dst, mask, a, b),
        Op::Un { op, ty, from, dst, a } => exec_un(regs, op, ty, from, dst, mask, a),
        Op::Tri { op, ty, dst, a, b, c } => exec_tri(regs, op, ty, dst, mask, a, b, c),
        Op::BitInsert { ty, dst, base, insert, offset, count } => {
            let (a, b, c, d) = (regs[base as usize], regs[insert as usize], regs[offset as usize], regs[count as usize]);
            lanes(regs, dst, mask, |l| alu::bit_insert(ty, a[l], b[l], c[l], d[l]));
        }
        Op::Select { dst, cond, a, b } => map3(regs, dst, mask, cond, a, b, |c, x, y| if c != 0 { x } else { y }),
        Op::Index { dst, base, index, index_ty: Sc::I32, stride } => {
            map2(regs, dst, mask, base, index, |b, i| b.wrapping_add((i as u32 as i32 as i64 as u64).wrapping_mul(stride)))
        }
        Op::Index { dst, base, index, stride, .. } => map2(regs, dst, mask, base, index, |b, i| b.wrapping_add(i.wrapping_mul(stride))),
        Op::AddImm { dst, a, imm } => map1(regs, dst, mask, a, |a| a.wrapping_add(imm)),
        Op::Load { .. } | Op::Store { .. } | Op::Atomic { .. } => super::exec_mem::exec_mem(ctx, group, wg, op, mask),
        Op::ImageRead { .. } | Op::ImageWrite { .. } | Op::ImageSize { .. } | Op::ImageTexel { .. } => super::exec_image::exec_image(ctx, group, wg, op, mask),
        Op::RayQuery(ref rq) => super::exec_rq::exec_ray_query(ctx, group, wg, rq, mask),
        Op::Subgroup { op, ty, dst, a, b } => {
            let (a, b) = (regs[a as usize], regs[b as usize]);
            let v = subgroup(op, ty, mask, &a, &b);
            lanes(regs, dst, mask, |l| v[l]);
        }
        Op::Ballot { dst, a } => {
            let a = regs[a as usize];
            let bits = (0..LANES).filter(|&l| on(mask, l) && a[l] != 0).fold(0u64, |acc, l| acc | 1 << l);
            lanes(regs, dst[0], mask, |_| bits);
            for &d in &dst[1..] {
                lanes(regs, d, mask, |_| 0);
            }
        }
        Op::BallotOp { op, dst, ballot, b } => {
            let (w, b) = (regs[ballot[0] as usize], regs[b as usize]);
            let all = (1u64 << LANES) - 1;
            lanes(regs, dst, mask, |l| {
                let bits = w[l] & all;
                match op {
                    BallotOp::Inverse => (bits >> l) & 1,
                    BallotOp::BitExtract => if b[l] < 32 { (w[l] >> b[l]) & 1 } else { 0 },
                    BallotOp::BitCountReduce => bits.count_ones() as u64,
                    BallotOp::BitCountInclusive => (bits & ((2u64 << l) - 1)).count_ones() as u64,
                    BallotOp::BitCountExclusive => (bits & ((1u64 << l) - 1)).count_ones() as u64,
                    BallotOp::FindLsb => if bits == 0 { 0xFFFF_FFFF } else { bits.trailing_zeros() as u64 },
                    BallotOp::FindMsb => if bits == 0 { 0xFFFF_FFFF } else { 63 - bits.leading_zeros() as u64 },
                }
            });
        }
    }
}

/// The identity of a scan's operation (the exclusive scan's first value).
fn identity(op: BinOp, ty: Sc) -> u64 {
    let fl = |x: f64| alu::from_f(ty, x);
    let wide = ty.bits() == 64;
    match op {
        BinOp::IMul => 1,
        BinOp::FMul => fl(1.0),
        BinOp::FAdd => fl(0.0),
        BinOp::FMin => fl(f64::INFINITY),
        BinOp::FMax => fl(f64::NEG_INFINITY),
        BinOp::UMin | BinOp::And => alu::norm(ty, u64::MAX),
        BinOp::SMin => if wide { i64::MAX as u64 } else { i32::MAX as u64 },
        BinOp::SMax => if wide { i64::MIN as u64 } else { i32::MIN as u32 as u64 },
        _ => 0,
    }
}

fn subgroup(op: SgOp, ty: Sc, mask: u32, a: &Regs, b: &Regs) -> Regs {
    let first = mask.trailing_zeros() as usize;
    let active = || (0..LANES).filter(move |&l| on(mask, l));
    let pick = |i: u64| a[(i as usize) % LANES];
    let mut out = [0u64; LANES];
    match op {
        SgOp::Elect => out[first.min(LANES - 1)] = 1,
        SgOp::All => out = [active().all(|l| a[l] != 0) as u64; LANES],
        SgOp::Any => out = [active().any(|l| a[l] != 0) as u64; LANES],
        SgOp::AllEqual => out = [active().all(|l| a[l] == a[first]) as u64; LANES],
        SgOp::Broadcast => out = [pick(b[first.min(LANES - 1)]); LANES],
        SgOp::BroadcastFirst => out = [a[first.min(LANES - 1)]; LANES],
        SgOp::Shuffle => out = std::array::from_fn(|l| pick(b[l])),
        SgOp::ShuffleXor => out = std::array::from_fn(|l| pick(l as u64 ^ b[l])),
        SgOp::ShuffleUp => out = std::array::from_fn(|l| pick((l as u64).wrapping_sub(b[l]))),
        SgOp::ShuffleDown => out = std::array::from_fn(|l| pick(l as u64 + b[l])),
        SgOp::Reduce(bop) => {
            let v = active().fold(identity(bop, ty), |acc, l| alu::bin(bop, ty, acc, a[l]));
            out = [v; LANES];
        }
        SgOp::InclusiveScan(bop) | SgOp::ExclusiveScan(bop) => {
            let inclusive = matches!(op, SgOp::InclusiveScan(_));
            let mut acc = identity(bop, ty);
            for l in active() {
                let next = alu::bin(bop, ty, acc, a[l]);
                out[l] = if inclusive { next } else { acc };
                acc = next;
            }
        }
    }
    out
}
