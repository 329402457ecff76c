//! Where a training step's device time goes, measured on the device: timestamps written
//! between the step's phases (`TIMESTAMP_QUERY_INSIDE_ENCODERS`), read back once a profiled
//! step ends. A phase's time is the gap from the timestamp before it to its own, so the
//! gap before each submission's first phase is the device's idle time while the host
//! waited or recorded. Profiling costs one extra read-back per profiled step; the trainer
//! profiles one step in `every`.

use super::{GpuContext, GpuResult};

/// Timestamps a step may write (phases × scenes + submissions; more are ignored).
const MAX_QUERIES: u32 = 256;
/// The label of the gap before a submission's first phase.
pub const IDLE: &str = "device idle (host waits and records)";

pub struct StepProfiler {
    set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    period_ns: f64,
    every: u32,
    /// This step's labels, one per timestamp written (the phase that ends there).
    labels: Vec<&'static str>,
    active: bool,
    /// Per phase: total nanoseconds over the profiled steps, in first-seen order.
    totals: Vec<(&'static str, f64)>,
    steps: u32,
}

impl StepProfiler {
    /// A profiler of one step in `every`, or `None` where the device cannot write
    /// timestamps inside encoders.
    pub fn new(ctx: &GpuContext, every: u32) -> Option<StepProfiler> {
        let need =
            wgpu::Features::TIMESTAMP_QUERY | wgpu::Features::TIMESTAMP_QUERY_INSIDE_ENCODERS;
        if every == 0 || !ctx.device.features().contains(need) {
            return None;
        }
        let set = ctx.device.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some("step timestamps"),
            ty: wgpu::QueryType::Timestamp,
            count: MAX_QUERIES,
        });
        let resolve = ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("step timestamps resolved"),
            size: 8 * MAX_QUERIES as u64,
            usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        Some(StepProfiler {
            set,
            resolve,
            period_ns: ctx.queue.get_timestamp_period() as f64,
            every,
            labels: Vec::new(),
            active: false,
            totals: Vec::new(),
            steps: 0,
        })
    }

    /// Starts step `step`: profiled when it is one in `every`.
    pub fn begin_step(&mut self, step: u32) {
        self.labels.clear();
        self.active = step.is_multiple_of(self.every);
    }

    /// Marks the start of a submission: the gap before it is the device's idle time.
    pub fn submission(&mut self, encoder: &mut wgpu::CommandEncoder) {
        self.mark(encoder, IDLE);
    }

    /// Marks the end of phase `label` in `encoder`.
    pub fn mark(&mut self, encoder: &mut wgpu::CommandEncoder, label: &'static str) {
        if !self.active || self.labels.len() as u32 >= MAX_QUERIES {
            return;
        }
        encoder.write_timestamp(&self.set, self.labels.len() as u32);
        self.labels.push(label);
    }

    /// Ends the step: reads the timestamps back (one wait) and adds its phases' times.
    pub fn end_step(&mut self, ctx: &GpuContext) -> GpuResult<()> {
        if !self.active || self.labels.len() < 2 {
            return Ok(());
        }
        let n = self.labels.len() as u32;
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        encoder.resolve_query_set(&self.set, 0..n, &self.resolve, 0);
        ctx.scoped("timestamps", || ctx.queue.submit([encoder.finish()]))?;
        let ts: Vec<u64> = ctx.read_buffer(&self.resolve, 8 * n as u64)?;
        // The first timestamp (the first submission's start) opens the step.
        for (i, &label) in self.labels.iter().enumerate().skip(1) {
            let dt = ts[i].saturating_sub(ts[i - 1]) as f64 * self.period_ns;
            match self.totals.iter_mut().find(|(l, _)| *l == label) {
                Some((_, t)) => *t += dt,
                None => self.totals.push((label, dt)),
            }
        }
        self.steps += 1;
        self.active = false;
        Ok(())
    }

    /// Milliseconds per profiled step, by phase, in the order the phases first ran.
    pub fn report(&self) -> Vec<(String, f64)> {
        let steps = self.steps.max(1) as f64;
        self.totals
            .iter()
            .map(|(l, ns)| (l.to_string(), ns / 1e6 / steps))
            .collect()
    }

    /// Whether the current step is profiled.
    pub fn is_active(&self) -> bool {
        self.active
    }
}
