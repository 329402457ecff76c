//! A training step's measurements, read back late (issue 29): what the host needs from a
//! step (each scene's batch and compaction counters, its summed loss and used samples, its
//! grid mean) lands in a small device buffer as the step runs, is copied at the step's end
//! into one slot of a ring of mappable buffers, and is read when a later step asks for it,
//! by which time the device has long finished it: the host records the next steps while
//! the device runs this one, as instant-ngp's own bookkeeping reads its counters late.
//!
//! `SUMS_WGSL` reduces a batch's per-ray (loss, samples used) pairs on the device in one
//! workgroup, in a fixed order: the same sums on every run.

use super::{GpuContext, GpuError, GpuResult, auto_layout_pipelines, buffer_entry as entry};
use std::collections::VecDeque;
use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};
use wgpu::util::DeviceExt;

/// u32 words a scene's measurements take: batch counters (asked, written, rays with
/// samples, rays dropped) at 0, compaction counters (asked, trained, rays that did not
/// fit, unused) at 4, loss sum (f32 bits) and samples used at 8, grid mean (f32 bits) at
/// 10.
pub const STAT_WORDS: u64 = 16;
pub const AT_BATCH: u64 = 0;
pub const AT_COMPACT: u64 = 4;
pub const AT_SUMS: u64 = 8;
pub const AT_MEAN: u64 = 10;

const SUMS_WGSL: &str = "
struct SumParams {
    n_rays: u32,
    // Word of stats to write (loss sum, then samples used).
    at: u32,
    _pad0: u32,
    _pad1: u32,
}
@group(0) @binding(0) var<storage, read> ray_out: array<vec2<f32>>;
@group(0) @binding(1) var<storage, read_write> stats: array<u32>;
@group(0) @binding(2) var<uniform> p: SumParams;
var<workgroup> loss_sh: array<f32, 256>;
var<workgroup> used_sh: array<u32, 256>;

@compute @workgroup_size(256)
fn sums_main(@builtin(local_invocation_index) lid: u32) {
    var l = 0.0;
    var u = 0u;
    for (var r = lid; r < p.n_rays; r += 256u) {
        let o = ray_out[r];
        l += o.x;
        u += bitcast<u32>(o.y);
    }
    loss_sh[lid] = l;
    used_sh[lid] = u;
    workgroupBarrier();
    for (var s = 128u; s > 0u; s >>= 1u) {
        if (lid < s) {
            loss_sh[lid] += loss_sh[lid + s];
            used_sh[lid] += used_sh[lid + s];
        }
        workgroupBarrier();
    }
    if (lid == 0u) {
        stats[p.at] = bitcast<u32>(loss_sh[0]);
        stats[p.at + 1u] = used_sh[0];
    }
}
";

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct SumParams {
    n_rays: u32,
    at: u32,
    _pad: [u32; 2],
}

/// One scene's measurements of one step.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SceneMeasure {
    pub scene: usize,
    /// Rays the step drew for the scene.
    pub n_rays: u32,
    pub batch: [u32; 4],
    pub compact: [u32; 4],
    pub loss_sum: f32,
    pub used: u32,
    pub grid_mean: f32,
}

/// A step's measurements.
#[derive(Clone, Debug, Default)]
pub struct StepMeasure {
    pub step: u32,
    pub scenes: Vec<SceneMeasure>,
}

const EMPTY: u8 = 0;
const MAPPED: u8 = 1;
const FAILED: u8 = 2;

struct Slot {
    buffer: wgpu::Buffer,
    state: Arc<AtomicU8>,
}

struct Pending {
    slot: usize,
    step: u32,
    scenes: Vec<(usize, u32)>,
    submission: wgpu::SubmissionIndex,
}

/// The device buffer the step writes, the ring it is copied into, and the steps in flight.
pub struct StepReadback {
    stats: wgpu::Buffer,
    n_scenes: usize,
    ring: Vec<Slot>,
    next: usize,
    pending: VecDeque<Pending>,
    sums: wgpu::ComputePipeline,
}

impl StepReadback {
    /// For `n_scenes` scenes and up to `in_flight` steps not yet read.
    pub fn new(ctx: &GpuContext, n_scenes: usize, in_flight: usize) -> GpuResult<Self> {
        let bytes = 4 * STAT_WORDS * n_scenes.max(1) as u64;
        ctx.scoped("step readback", || {
            let d = &ctx.device;
            let [sums] = auto_layout_pipelines(ctx, "ray sums", SUMS_WGSL, ["sums_main"]);
            StepReadback {
                stats: d.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("step measurements"),
                    size: bytes,
                    usage: wgpu::BufferUsages::STORAGE
                        | wgpu::BufferUsages::COPY_SRC
                        | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                }),
                n_scenes,
                ring: (0..in_flight.max(1) + 1)
                    .map(|_| Slot {
                        buffer: d.create_buffer(&wgpu::BufferDescriptor {
                            label: Some("step measurements ring"),
                            size: bytes,
                            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                            mapped_at_creation: false,
                        }),
                        state: Arc::new(AtomicU8::new(EMPTY)),
                    })
                    .collect(),
                next: 0,
                pending: VecDeque::new(),
                sums,
            }
        })
    }

    /// Steps recorded and not yet read.
    pub fn in_flight(&self) -> usize {
        self.pending.len()
    }

    /// The step of the oldest measurement not yet read.
    pub fn oldest(&self) -> Option<u32> {
        self.pending.front().map(|p| p.step)
    }

    /// Records scene `si`'s measurements into the step's buffer: `counters` (the batch's
    /// four) and `compact` (the compaction's four) copied, the per-ray pairs of `n_rays`
    /// rays in `ray_out` summed, the grid mean (the f32 at byte 0 of `mean`) copied.
    #[allow(clippy::too_many_arguments)]
    pub fn encode_scene(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        si: usize,
        counters: &wgpu::Buffer,
        compact: &wgpu::Buffer,
        ray_out: &wgpu::Buffer,
        n_rays: u32,
        mean: &wgpu::Buffer,
    ) -> GpuResult<()> {
        if si >= self.n_scenes || u64::from(n_rays) * 8 > ray_out.size() {
            return Err(GpuError::Input(format!(
                "measurements of scene {si} of {}, {n_rays} rays",
                self.n_scenes
            )));
        }
        let base = 4 * STAT_WORDS * si as u64;
        encoder.copy_buffer_to_buffer(counters, 0, &self.stats, base + 4 * AT_BATCH, 16);
        encoder.copy_buffer_to_buffer(compact, 0, &self.stats, base + 4 * AT_COMPACT, 16);
        encoder.copy_buffer_to_buffer(mean, 0, &self.stats, base + 4 * AT_MEAN, 4);
        ctx.scoped("ray sums", || {
            let p = ctx
                .device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("ray sums params"),
                    contents: bytemuck::bytes_of(&SumParams {
                        n_rays,
                        at: (STAT_WORDS * si as u64 + AT_SUMS) as u32,
                        _pad: [0; 2],
                    }),
                    usage: wgpu::BufferUsages::UNIFORM,
                });
            let group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("ray sums"),
                layout: &self.sums.get_bind_group_layout(0),
                entries: &[entry(0, ray_out), entry(1, &self.stats), entry(2, &p)],
            });
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.sums);
            pass.set_bind_group(0, &group, &[]);
            pass.dispatch_workgroups(1, 1, 1);
        })
    }

    /// Records the copy of the step's measurements into the next ring slot; call
    /// [`Self::submitted`] once the encoder is submitted. An error if every slot is in
    /// flight (read some first).
    pub fn encode_copy(&self, encoder: &mut wgpu::CommandEncoder) -> GpuResult<()> {
        if self.pending.len() >= self.ring.len() {
            return Err(GpuError::Input(format!(
                "{} steps' measurements in flight: the ring holds {}",
                self.pending.len(),
                self.ring.len()
            )));
        }
        let slot = &self.ring[self.next];
        encoder.copy_buffer_to_buffer(&self.stats, 0, &slot.buffer, 0, self.stats.size());
        Ok(())
    }

    /// The step whose copy [`Self::encode_copy`] recorded was submitted as `submission`;
    /// `scenes` are the (scene, rays drawn) it trained, in order.
    pub fn submitted(
        &mut self,
        step: u32,
        scenes: Vec<(usize, u32)>,
        submission: wgpu::SubmissionIndex,
    ) {
        let slot = &self.ring[self.next];
        slot.state.store(EMPTY, Ordering::Release);
        let state = slot.state.clone();
        slot.buffer.map_async(wgpu::MapMode::Read, .., move |r| {
            state.store(if r.is_ok() { MAPPED } else { FAILED }, Ordering::Release);
        });
        self.pending.push_back(Pending {
            slot: self.next,
            step,
            scenes,
            submission,
        });
        self.next = (self.next + 1) % self.ring.len();
    }

    /// The oldest step's measurements, waiting for the device only if they are not there
    /// yet (`waited` says whether it had to). `None` if nothing is in flight.
    pub fn read_oldest(&mut self, ctx: &GpuContext) -> GpuResult<Option<(StepMeasure, bool)>> {
        let Some(p) = self.pending.pop_front() else {
            return Ok(None);
        };
        let slot = &self.ring[p.slot];
        let device_err = |msg: String| GpuError::Device {
            what: "step measurements",
            msg,
        };
        let _ = ctx.device.poll(wgpu::PollType::Poll);
        let mut waited = false;
        if slot.state.load(Ordering::Acquire) == EMPTY {
            waited = true;
            ctx.device
                .poll(wgpu::PollType::Wait {
                    submission_index: Some(p.submission),
                    timeout: None,
                })
                .map_err(|e| device_err(e.to_string()))?;
            // Another thread polling the same device may be the one running the callback:
            // give it the moment it takes.
            let t = std::time::Instant::now();
            while slot.state.load(Ordering::Acquire) == EMPTY
                && t.elapsed() < std::time::Duration::from_secs(10)
            {
                std::thread::yield_now();
                let _ = ctx.device.poll(wgpu::PollType::Poll);
            }
        }
        if slot.state.load(Ordering::Acquire) != MAPPED {
            return Err(device_err(format!(
                "the measurements could not be mapped (state {})",
                slot.state.load(Ordering::Acquire)
            )));
        }
        let words: Vec<u32> = {
            let view = slot
                .buffer
                .get_mapped_range(..)
                .map_err(|e| device_err(e.to_string()))?;
            bytemuck::cast_slice(&view).to_vec()
        };
        slot.buffer.unmap();
        slot.state.store(EMPTY, Ordering::Release);
        let scenes = p
            .scenes
            .iter()
            .map(|&(si, n_rays)| {
                let w = &words[(STAT_WORDS as usize) * si..][..STAT_WORDS as usize];
                let four = |at: u64| [0, 1, 2, 3].map(|i| w[at as usize + i]);
                SceneMeasure {
                    scene: si,
                    n_rays,
                    batch: four(AT_BATCH),
                    compact: four(AT_COMPACT),
                    loss_sum: f32::from_bits(w[AT_SUMS as usize]),
                    used: w[AT_SUMS as usize + 1],
                    grid_mean: f32::from_bits(w[AT_MEAN as usize]),
                }
            })
            .collect();
        Ok(Some((
            StepMeasure {
                step: p.step,
                scenes,
            },
            waited,
        )))
    }
}
