//! Fewer blocks for the scheduler to step through: every block a lane group runs costs a
//! scheduling step (the lowest cursor, the branch per lane), and unoptimised SPIR-V spends one
//! on every `if`, every `&&` and every loop latch, each holding one or two ops.
//!
//! - If-conversion: a two-way branch whose arms are small, side-effect-free single blocks that
//!   meet again (a diamond, or a triangle where one edge goes straight to the merge) becomes
//!   straight-line code: both arms run for every lane of the mask into fresh registers, and a
//!   `Select` on the branch condition writes back each register an arm changed (phi
//!   temporaries filled on the edges included). Only ops that cannot fault or touch memory are
//!   speculated: ALU ops (integer division by zero is total in `alu`) and loads of push
//!   constants or of the lane frame at constant in-range addresses. Stores, atomics, other
//!   loads, image and ray-query ops, and subgroup ops (which see the execution mask) keep
//!   their branch.
//! - Merging: a block reached only by a jump from one other block is appended to it.
//! - Loop rotation: a jump back to a small loop header whose test is a two-way branch copies
//!   the header into the jumping block, so a loop whose lanes keep going runs one block per
//!   round.
//!
//! Lanes compute the same values either way; what changes is only which lanes share a step,
//! which no op outside the subgroup family can observe, and blocks holding subgroup ops are
//! neither merged nor copied. Blocks that lose their last predecessor stay in place, unreached,
//! so block indices (and the structured order) do not move.
use std::collections::HashMap;

use super::ir::{Block, Op, Reg, Space, Term};
use super::lower_copies::{reads, replace_reads, result_mut, writes};

/// Ops per arm that if-conversion runs for every lane of the mask.
const MAX_ARM_OPS: usize = 16;
/// Ops of a loop header copied into a jump back to it.
const MAX_HEADER_OPS: usize = 24;
/// Rounds of the whole pass (each may enable more in the next).
const MAX_ROUNDS: usize = 8;

/// What speculated loads may read without faulting.
pub(super) struct Bounds {
    /// Bytes of push constants the program reads (the dispatch pads shorter data with zeros).
    pub push: u32,
    /// Bytes of one lane's frame.
    pub frame: u32,
}

struct Cfg {
    preds: Vec<u32>,
    reachable: Vec<bool>,
    uses: Vec<u32>,
    defs: Vec<u32>,
}

pub(super) fn simplify(blocks: &mut [Block], reg_count: &mut u32, consts: &mut Vec<(Reg, u64)>, bounds: &Bounds) {
    fold_offsets(blocks, *reg_count, consts);
    let consts_list = consts.clone();
    let consts: HashMap<Reg, u64> = consts_list.iter().copied().collect();
    hoist_push_loads(blocks, *reg_count, &consts, bounds);
    for _ in 0..MAX_ROUNDS {
        let mut changed = false;
        let mut cfg = analyse(blocks, *reg_count);
        for h in 0..blocks.len() {
            while cfg.reachable[h] && (if_convert(blocks, h, &cfg, reg_count, &consts, bounds) || merge(blocks, h, &cfg.preds)) {
                changed = true;
                cfg = analyse(blocks, *reg_count);
            }
        }
        // Copies left by merged blocks go before headers are copied, so the copies do not
        // define their registers twice.
        super::lower_copies::forward(blocks, *reg_count, &consts_list);
        for x in 0..blocks.len() {
            changed |= cfg.reachable[x] && rotate(blocks, x);
        }
        if !changed {
            break;
        }
    }
    // Unreached blocks go empty, so later passes count no uses in them.
    let cfg = analyse(blocks, *reg_count);
    for (b, _) in blocks.iter_mut().zip(&cfg.reachable).filter(|(_, r)| !**r) {
        *b = Block { ops: Vec::new(), term: Term::Exit, phi_in: Vec::new(), edge_moves: Vec::new() };
    }
}

/// Constant offsets from constant addresses (a push-constant member, a lane variable's field)
/// become constants themselves: one op less, and loads through them count as in range.
fn fold_offsets(blocks: &mut [Block], reg_count: u32, consts: &mut Vec<(Reg, u64)>) {
    let mut defs = vec![0u32; reg_count as usize];
    for b in blocks.iter() {
        b.phi_in.iter().for_each(|&(d, _)| defs[d as usize] += 1);
        b.ops.iter().for_each(|op| writes(op, &mut |r| defs[r as usize] += 1));
        b.edge_moves.iter().for_each(|m| defs[m.dst as usize] += 1);
    }
    let mut known: HashMap<Reg, u64> = consts.iter().copied().collect();
    for b in blocks.iter_mut() {
        b.ops.retain(|op| match *op {
            Op::AddImm { dst, a, imm } if defs[dst as usize] == 1 && known.contains_key(&a) => {
                let v = known[&a].wrapping_add(imm);
                known.insert(dst, v);
                consts.push((dst, v));
                false
            }
            _ => true,
        });
    }
}

/// Push constants do not change during a dispatch: loads of them at constant in-range
/// addresses move to the start of the entry block, which every lane runs first, so loops do
/// not repeat them and arms holding them can be converted.
fn hoist_push_loads(blocks: &mut [Block], reg_count: u32, consts: &HashMap<Reg, u64>, bounds: &Bounds) {
    let mut defs = vec![0u32; reg_count as usize];
    for b in blocks.iter() {
        b.phi_in.iter().for_each(|&(d, _)| defs[d as usize] += 1);
        b.ops.iter().for_each(|op| writes(op, &mut |r| defs[r as usize] += 1));
        b.edge_moves.iter().for_each(|m| defs[m.dst as usize] += 1);
    }
    let mut hoisted = Vec::new();
    for b in blocks.iter_mut().skip(1) {
        b.ops.retain(|op| match *op {
            Op::Load { space: Space::Push, dst, .. } if defs[dst as usize] == 1 && speculable(op, consts, bounds) => {
                hoisted.push(op.clone());
                false
            }
            _ => true,
        });
    }
    if let Some(entry) = blocks.first_mut() {
        entry.ops.splice(0..0, hoisted);
    }
}

fn successors(t: &Term) -> Vec<u32> {
    match t {
        Term::Jump(t) | Term::Barrier(t) => vec![*t],
        Term::Cond { t, f, .. } => vec![*t, *f],
        Term::Switch { default, cases, .. } => std::iter::once(*default).chain(cases.iter().map(|c| c.1)).collect(),
        Term::Exit => Vec::new(),
    }
}

/// Predecessor counts from reachable blocks (the entry counts one more), and register use and
/// definition counts over the reachable blocks.
fn analyse(blocks: &[Block], reg_count: u32) -> Cfg {
    let n = blocks.len();
    let mut cfg = Cfg { preds: vec![0; n], reachable: vec![false; n], uses: vec![0; reg_count as usize], defs: vec![0; reg_count as usize] };
    if n == 0 {
        return cfg;
    }
    cfg.preds[0] = 1;
    let mut stack = vec![0usize];
    cfg.reachable[0] = true;
    while let Some(b) = stack.pop() {
        let block = &blocks[b];
        for s in successors(&block.term) {
            cfg.preds[s as usize] += 1;
            if !cfg.reachable[s as usize] {
                cfg.reachable[s as usize] = true;
                stack.push(s as usize);
            }
        }
        for &(d, t) in &block.phi_in {
            cfg.defs[d as usize] += 1;
            cfg.uses[t as usize] += 1;
        }
        for op in &block.ops {
            reads(op, &mut |r| cfg.uses[r as usize] += 1);
            writes(op, &mut |r| cfg.defs[r as usize] += 1);
        }
        for m in &block.edge_moves {
            cfg.defs[m.dst as usize] += 1;
            cfg.uses[m.src as usize] += 1;
        }
        match block.term {
            Term::Cond { cond: r, .. } | Term::Switch { sel: r, .. } => cfg.uses[r as usize] += 1,
            _ => {}
        }
    }
    cfg
}

/// Whether `op` may run for a lane whose branch did not choose it: it changes only its
/// result register and cannot fault.
fn speculable(op: &Op, consts: &HashMap<Reg, u64>, bounds: &Bounds) -> bool {
    match *op {
        Op::Mov { .. } | Op::Un { .. } | Op::Bin { .. } | Op::Tri { .. } | Op::BitInsert { .. } | Op::Select { .. } | Op::Index { .. } | Op::AddImm { .. } => true,
        Op::Load { ty, space, addr, .. } => {
            let limit = match space {
                Space::Push => bounds.push,
                Space::Lane => bounds.frame,
                _ => return false,
            };
            consts.get(&addr).is_some_and(|&a| a.checked_add(ty.size() as u64).is_some_and(|end| end <= limit as u64))
        }
        _ => false,
    }
}

/// Ops the execution mask is visible to: the blocks holding them keep their own step.
fn sees_mask(op: &Op) -> bool {
    matches!(op, Op::Subgroup { .. } | Op::Ballot { .. } | Op::BallotOp { .. })
}

/// One side of a branch: the ops it runs (the edge's phi moves as trailing `Mov`s).
type Side = Vec<Op>;

/// An arm of block `h`'s branch: a block entered only from `h`, without phis, of speculable
/// ops, that jumps on. Returns where it jumps and its side.
fn arm(blocks: &[Block], h: usize, x: u32, cfg: &Cfg, consts: &HashMap<Reg, u64>, bounds: &Bounds) -> Option<(u32, Side)> {
    let b = &blocks[x as usize];
    let Term::Jump(m) = b.term else { return None };
    let ok = x as usize != h
        && m != x
        && cfg.preds[x as usize] == 1
        && b.phi_in.is_empty()
        && b.ops.len() <= MAX_ARM_OPS
        && b.ops.iter().all(|op| speculable(op, consts, bounds));
    ok.then(|| (m, b.ops.iter().cloned().chain(b.edge_moves.iter().map(|e| Op::Mov { dst: e.dst, src: e.src })).collect()))
}

/// The moves of `h`'s edges to `target`, as a side.
fn edge_side(b: &Block, target: u32) -> Side {
    b.edge_moves.iter().filter(|e| e.target == target).map(|e| Op::Mov { dst: e.dst, src: e.src }).collect()
}

fn if_convert(blocks: &mut [Block], h: usize, cfg: &Cfg, reg_count: &mut u32, consts: &HashMap<Reg, u64>, bounds: &Bounds) -> bool {
    let Term::Cond { cond, t, f } = blocks[h].term else { return false };
    if t == f {
        blocks[h].term = Term::Jump(t);
        return true;
    }
    let (at, af) = (arm(blocks, h, t, cfg, consts, bounds), arm(blocks, h, f, cfg, consts, bounds));
    let (merge, side_t, side_f) = match (at, af) {
        (Some((mt, st)), Some((mf, sf))) if mt == mf => (mt, st, sf),
        (Some((mt, st)), _) if mt == f => (f, st, edge_side(&blocks[h], f)),
        (_, Some((mf, sf))) if mf == t => (t, edge_side(&blocks[h], t), sf),
        _ => return false,
    };
    // Forward merges only: a branch back to a loop header is the loop's, not an `if`.
    if merge as usize <= h || blocks[h].edge_moves.iter().any(|e| e.target != merge) {
        return false;
    }
    let ops = straighten(cond, &side_t, &side_f, cfg, reg_count);
    let block = &mut blocks[h];
    block.ops.extend(ops);
    block.edge_moves.clear();
    block.term = Term::Jump(merge);
    true
}

/// Both sides renamed into fresh registers, then one `Select` per register either side
/// changes that is live past the branch: `r = cond ? r_t : r_f` (a side that leaves `r` alone
/// gives `r` itself). Copies inside a side are followed instead of run, unless they read a
/// register the selects change (which would then read a changed value).
fn straighten(cond: Reg, side_t: &Side, side_f: &Side, cfg: &Cfg, reg_count: &mut u32) -> Vec<Op> {
    let mut written: Vec<Reg> = Vec::new();
    for op in side_t.iter().chain(side_f) {
        writes(op, &mut |r| {
            if !written.contains(&r) {
                written.push(r);
            }
        });
    }
    let mut out = Vec::new();
    let mut rename = |side: &Side, out: &mut Vec<Op>| {
        let mut map: HashMap<Reg, Reg> = HashMap::new();
        for op in side {
            let mut op = op.clone();
            rename_reads(&mut op, &map);
            if let Op::Mov { dst, src } = op {
                if !written.contains(&src) {
                    map.insert(dst, src);
                    continue;
                }
            }
            let fresh = *reg_count;
            *reg_count += 1;
            if let Some(d) = result_mut(&mut op) {
                map.insert(std::mem::replace(d, fresh), fresh);
            }
            out.push(op);
        }
        map
    };
    let (map_t, map_f) = (rename(side_t, &mut out), rename(side_f, &mut out));
    // Registers defined once, with every use inside one side, die with the branch.
    let local = |r: Reg| {
        let inside = |side: &Side| {
            let mut n = 0;
            side.iter().for_each(|op| reads(op, &mut |x| n += (x == r) as u32));
            n
        };
        cfg.defs.get(r as usize) == Some(&1) && cfg.uses.get(r as usize).is_some_and(|&u| u == inside(side_t) || u == inside(side_f))
    };
    // The condition's own select goes last: the others read it.
    written.sort_by_key(|&r| r == cond);
    for r in written.into_iter().filter(|&r| !local(r)) {
        let (a, b) = (map_t.get(&r).copied().unwrap_or(r), map_f.get(&r).copied().unwrap_or(r));
        out.push(Op::Select { dst: r, cond, a, b });
    }
    out
}

fn rename_reads(op: &mut Op, map: &HashMap<Reg, Reg>) {
    let mut from = Vec::new();
    reads(op, &mut |r| {
        if map.contains_key(&r) && !from.contains(&r) {
            from.push(r);
        }
    });
    // No value of the map is also a key (values are fresh registers or registers neither side
    // writes), so one replacement per register suffices.
    for r in from {
        replace_reads(op, r, map[&r]);
    }
}

/// The moves that entering `to` from the end of `from` performs, as ops: the edge's phi
/// temporaries, then the phi registers from them.
fn entry_moves(from: &Block, to_index: u32, to: &Block) -> Vec<Op> {
    let edge = from.edge_moves.iter().filter(|e| e.target == to_index).map(|e| Op::Mov { dst: e.dst, src: e.src });
    edge.chain(to.phi_in.iter().map(|&(dst, src)| Op::Mov { dst, src })).collect()
}

/// Appends the block `h` jumps to, when `h` is its only predecessor.
fn merge(blocks: &mut [Block], h: usize, preds: &[u32]) -> bool {
    let Term::Jump(y) = blocks[h].term else { return false };
    let yu = y as usize;
    if yu == h || preds[yu] != 1 || blocks[yu].ops.iter().any(sees_mask) {
        return false;
    }
    let next = std::mem::replace(&mut blocks[yu], Block { ops: Vec::new(), term: Term::Exit, phi_in: Vec::new(), edge_moves: Vec::new() });
    let moves = entry_moves(&blocks[h], y, &next);
    let block = &mut blocks[h];
    block.ops.extend(moves);
    block.ops.extend(next.ops);
    block.term = next.term;
    block.edge_moves = next.edge_moves;
    true
}

/// A jump back to a loop header that tests and branches: the header's ops and branch are
/// copied to the end of the jumping block.
fn rotate(blocks: &mut [Block], x: usize) -> bool {
    let Term::Jump(t) = blocks[x].term else { return false };
    let header = &blocks[t as usize];
    let small = header.ops.len() <= MAX_HEADER_OPS && !header.ops.iter().any(sees_mask);
    if t as usize >= x || !small || !matches!(header.term, Term::Cond { .. }) {
        return false;
    }
    let header = header.clone();
    let moves = entry_moves(&blocks[x], t, &header);
    let block = &mut blocks[x];
    block.ops.extend(moves);
    block.ops.extend(header.ops);
    block.term = header.term;
    block.edge_moves = header.edge_moves;
    true
}

#[cfg(test)]
mod tests {
    use crate::shader::ir::Term;
    use crate::shader::tests::compile_with;
    use crate::shader::{dispatch, HostMemory, Module, Pipeline, Watchdog, LANES};

    fn pipeline(words: &[u32]) -> Pipeline {
        Pipeline::compute(&Module::parse(words).unwrap(), "main", &[]).unwrap()
    }

    /// tests/shaders/if_convert.comp computed on the CPU: `r[i]`, and `r[n + i]` where the
    /// shader stores it.
    fn reference(v: &[u32], n: usize, k: u32) -> (Vec<u32>, Vec<Option<u32>>) {
        let (mut out, mut stored) = (vec![0; n], vec![None; n]);
        for i in 0..n {
            let a = v[i];
            let b = a.wrapping_mul(2654435761);
            let mut c = a.checked_div(b & 7).unwrap_or(a.wrapping_add(k));
            if a > k {
                c = c.wrapping_add(a % 13);
            }
            let p = a & 16 != 0 && (b >> 28) > 3;
            let q = a & 32 != 0 || c < 1000;
            let mut d = if p { 5 } else { 0 } + if q { 7 } else { 0 };
            if p {
                d += if q { 100 } else { 200 };
            }
            let (u, w) = if a & 128 != 0 { (b, a) } else { (a, b) };
            if a & 64 != 0 {
                stored[i] = Some(c);
            }
            // subgroupAdd(1) over the lanes of i's lane group that take the branch.
            let group = (i / LANES) * LANES..((i / LANES + 1) * LANES).min(n);
            let e = if a & 1 != 0 { group.filter(|&j| v[j] & 1 != 0).count() as u32 } else { 0 };
            let mut s = 0u32;
            for j in 0..(a & 31) {
                if j & 3 == 2 {
                    continue;
                }
                if s > 200 + k {
                    break;
                }
                s = s.wrapping_add(j.wrapping_mul(c & 7));
            }
            let (mut x, mut steps) = (a.wrapping_add(1), 0u32);
            while x > 1 && steps < 64 {
                x = if x & 1 != 0 { x.wrapping_mul(3).wrapping_add(1) } else { x >> 1 };
                steps += 1;
            }
            out[i] = c ^ (d << 8) ^ (s << 12) ^ (steps << 24) ^ u.wrapping_sub(w) ^ (e << 20);
        }
        (out, stored)
    }

    #[test]
    fn converted_branches_compute_what_the_branches_did() {
        let (n, k) = (1000usize, 500u32);
        // Magnitudes from 0 to 2^32 so that every branch splits lane groups both ways.
        let mut h = 0x9E37_79B9u32;
        let v: Vec<u32> = (0..n)
            .map(|_| {
                h = h.wrapping_mul(1664525).wrapping_add(1013904223);
                h >> (h % 29)
            })
            .collect();
        let (want, stored) = reference(&v, n, k);
        let bytes = |w: &[u32]| w.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
        let push = bytes(&[n as u32, k]);
        for (name, words) in compile_with("if_convert.comp", &[]) {
            let mut mem = HostMemory::new();
            let out = mem.add_buffer(&bytes(&vec![0xDEAD_BEEF; 2 * n]));
            let input = mem.add_buffer(&bytes(&v));
            mem.bind(0, 0, out);
            mem.bind(0, 1, input);
            let report = dispatch(&pipeline(&words), &mem, &push, [n.div_ceil(64) as u32, 1, 1], [0; 3], &Watchdog::default());
            assert!(report.is_clean(), "{name}: {report:?}");
            let got: Vec<u32> = mem.bytes(out).chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect();
            for i in 0..n {
                assert_eq!(got[i], want[i], "{name}: invocation {i} (input {:#x})", v[i]);
                assert_eq!(got[n + i], stored[i].unwrap_or(0xDEAD_BEEF), "{name}: store of invocation {i}");
            }
        }
    }

    /// The divergent benchmark's Collatz loop, as glslang emits it (a loop header, a `&&`, an
    /// if/else and a latch: nine blocks a round), runs as one block that branches to itself.
    #[test]
    fn the_collatz_loop_is_one_block() {
        let bytes = std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/bench/shaders/compute_divergent.spv")).unwrap();
        let words: Vec<u32> = bytes.chunks(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        let p = pipeline(&words);
        let self_loops = p.program.blocks.iter().enumerate().filter(|(i, b)| matches!(b.term, Term::Cond { t, .. } if t as usize == *i)).count();
        assert_eq!(self_loops, 1, "{:#?}", p.program.blocks);
    }

    #[test]
    fn speculated_push_constant_loads_read_zero_past_the_data_given() {
        // Only `n` is given: `k` (read in arms) reads as zero, as the runtime pads it.
        let (n, v) = (64usize, (0..64u32).map(|i| i * 7919).collect::<Vec<_>>());
        let (want, _) = reference(&v, n, 0);
        for (name, words) in compile_with("if_convert.comp", &[]) {
            let mut mem = HostMemory::new();
            let out = mem.add_buffer(&vec![0; 8 * n]);
            let input = mem.add_buffer(&v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>());
            mem.bind(0, 0, out);
            mem.bind(0, 1, input);
            let report = dispatch(&pipeline(&words), &mem, &(n as u32).to_le_bytes(), [1, 1, 1], [0; 3], &Watchdog::default());
            assert!(report.is_clean(), "{name}: {report:?}");
            let got: Vec<u32> = mem.bytes(out).chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect();
            assert_eq!(&got[..n], &want[..], "{name}");
        }
    }
}
