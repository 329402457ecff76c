//! The hooks' gradient mechanisms on the device (`held.wgsl`): the gate with hold-back,
//! the table's bounds ([`ngp::train::hooks`]), and the kept MLP gradient, for a gradient that
//! lives in a GPU buffer. The CPU opens the gate where a worker partial's sum is not zero;
//! here the summed gradient decides, which is the rule the optimizer applies to a zero
//! gradient on both backends.

use super::{
    GpuContext, GpuError, GpuResult, auto_layout_pipelines, buffer_entry as entry, check_binding,
    device_buffer,
};

use ngp::train::hooks::{TableBounds, UNBOUNDED};

const HELD_WGSL: &str = include_str!("held.wgsl");
const WORKGROUP: u32 = 256;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct HeldParams {
    n_table: u32,
    n_matrix: u32,
    row_width: u32,
    n_features: u32,
}

/// The gate and the held-back gradients of the table parameters `n_matrix..n_params`, and
/// the table's bounds.
pub struct GpuHoldBack {
    gate: wgpu::Buffer,
    pending: wgpu::Buffer,
    /// Per table entry: its bound, or [`UNBOUNDED`].
    bound: wgpu::Buffer,
    uniform: wgpu::Buffer,
    open: wgpu::ComputePipeline,
    hold: wgpu::ComputePipeline,
    clamp: wgpu::ComputePipeline,
    groups: [u32; 2],
    n_params: u32,
}

impl GpuHoldBack {
    pub fn new(
        ctx: &GpuContext,
        n_params: usize,
        n_matrix: usize,
        n_features: usize,
    ) -> GpuResult<GpuHoldBack> {
        let n_table = n_params
            .checked_sub(n_matrix)
            .and_then(|n| u32::try_from(n).ok())
            .filter(|&n| n > 0)
            .ok_or_else(|| {
                GpuError::Input(format!("{n_matrix} matrix parameters of {n_params}"))
            })?;
        check_binding(ctx, "held-back table gradients", 4 * n_table as u64)?;
        if n_features == 0 || !(n_table as usize).is_multiple_of(n_features) {
            return Err(GpuError::Input(format!(
                "{n_table} table parameters in entries of {n_features}"
            )));
        }
        let n_entries = n_table as usize / n_features;
        let limits = ctx.device.limits();
        let n_groups = n_table.div_ceil(WORKGROUP);
        let gx = n_groups.min(limits.max_compute_workgroups_per_dimension);
        let groups = [gx, n_groups.div_ceil(gx)];
        let params = HeldParams {
            n_table,
            n_matrix: n_matrix as u32,
            row_width: gx * WORKGROUP,
            n_features: n_features as u32,
        };
        ctx.scoped("hold-back kernels", || {
            let [open, hold, clamp] = auto_layout_pipelines(
                ctx,
                "held.wgsl",
                HELD_WGSL,
                ["open_gate", "hold_back", "clamp_bounded"],
            );
            let bound = device_buffer(ctx, "table bounds", 4 * n_entries as u64);
            ctx.queue
                .write_buffer(&bound, 0, bytemuck::cast_slice(&vec![UNBOUNDED; n_entries]));
            let uniform = ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("hold-back params"),
                size: std::mem::size_of::<HeldParams>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            ctx.queue
                .write_buffer(&uniform, 0, bytemuck::bytes_of(&params));
            GpuHoldBack {
                // Zeroed at creation (wgpu's guarantee): no gate open, nothing held.
                gate: device_buffer(ctx, "gate", 4 * n_table as u64),
                pending: device_buffer(ctx, "held-back gradients", 4 * n_table as u64),
                bound,
                uniform,
                open,
                hold,
                clamp,
                groups,
                n_params: n_params as u32,
            }
        })
    }

    fn encode(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        pipeline: &wgpu::ComputePipeline,
        grad: &wgpu::Buffer,
        with_pending: bool,
    ) -> GpuResult<()> {
        if grad.size() < 4 * self.n_params as u64 {
            return Err(GpuError::Input(format!(
                "gradient buffer of {} bytes for {} parameters",
                grad.size(),
                self.n_params
            )));
        }
        ctx.scoped("hold-back", || {
            // Each pipeline's layout is derived from what its entry point uses: the gate
            // kernel has no held-back gradients.
            let mut entries = vec![entry(0, grad), entry(1, &self.gate)];
            if with_pending {
                entries.push(entry(2, &self.pending));
                entries.push(entry(4, &self.bound));
            }
            entries.push(entry(3, &self.uniform));
            let bind_group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("hold-back"),
                layout: &pipeline.get_bind_group_layout(0),
                entries: &entries,
            });
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups(self.groups[0], self.groups[1], 1);
        })
    }

    /// Opens the gate of every table parameter the gradient so far reaches.
    pub fn encode_open_gate(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        grad: &wgpu::Buffer,
    ) -> GpuResult<()> {
        self.encode(ctx, encoder, &self.open, grad, false)
    }

    /// Holds back the gradients the gate keeps out (bounded entries excepted), releases the
    /// held-back gradients it lets through, and closes the gate.
    pub fn encode_hold_back(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        grad: &wgpu::Buffer,
    ) -> GpuResult<()> {
        self.encode(ctx, encoder, &self.hold, grad, true)
    }

    /// The table's bounds ([`TableBounds::bounds`]), after a policy changed them.
    pub fn upload_bounds(&self, ctx: &GpuContext, bounds: &TableBounds) -> GpuResult<()> {
        let b = bounds.bounds();
        if 4 * b.len() as u64 != self.bound.size() {
            return Err(GpuError::Input(format!(
                "{} entry bounds for a buffer of {} bytes",
                b.len(),
                self.bound.size()
            )));
        }
        ctx.scoped("table bounds", || {
            ctx.queue
                .write_buffer(&self.bound, 0, bytemuck::cast_slice(b))
        })
    }

    /// After Adam: holds every bounded entry within its bound.
    pub fn encode_clamp(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        weights: &wgpu::Buffer,
    ) -> GpuResult<()> {
        if weights.size() < 4 * self.n_params as u64 {
            return Err(GpuError::Input(format!(
                "weight buffer of {} bytes for {} parameters",
                weights.size(),
                self.n_params
            )));
        }
        ctx.scoped("table bounds' clamp", || {
            let bind_group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("table bounds' clamp"),
                layout: &self.clamp.get_bind_group_layout(0),
                entries: &[
                    entry(3, &self.uniform),
                    entry(4, &self.bound),
                    entry(5, weights),
                ],
            });
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.clamp);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups(self.groups[0], self.groups[1], 1);
        })
    }

    /// Sets the held-back gradients (a restored training state's).
    pub fn restore_pending(&self, ctx: &GpuContext, pending: &[f32]) -> GpuResult<()> {
        if 4 * pending.len() as u64 != self.pending.size() {
            return Err(GpuError::Input(format!(
                "{} held-back gradients for a buffer of {} bytes",
                pending.len(),
                self.pending.size()
            )));
        }
        ctx.scoped("held-back gradients", || {
            ctx.queue
                .write_buffer(&self.pending, 0, bytemuck::cast_slice(pending))
        })
    }

    /// The held-back gradients, read back (for tests and training states).
    pub fn pending(&self, ctx: &GpuContext) -> GpuResult<Vec<f32>> {
        ctx.read_buffer(&self.pending, self.pending.size())
    }
}

/// The kept MLP gradient on the device ([`ngp::train::hooks::PolicyOps::keep_mlp`]): the
/// gradient's MLP block (its first `n_matrix` parameters) copied aside and copied back,
/// or cleared in a step where nothing was kept.
pub struct GpuKeptMlp {
    kept: wgpu::Buffer,
    bytes: u64,
    any: bool,
}

impl GpuKeptMlp {
    pub fn new(ctx: &GpuContext, n_matrix: usize) -> GpuResult<GpuKeptMlp> {
        let bytes = 4 * n_matrix as u64;
        if bytes == 0 {
            return Err(GpuError::Input("an MLP of 0 parameters".into()));
        }
        check_binding(ctx, "the kept MLP gradient", bytes)?;
        Ok(GpuKeptMlp {
            kept: ctx.scoped("kept MLP gradient", || {
                device_buffer(ctx, "kept MLP gradient", bytes)
            })?,
            bytes,
            any: false,
        })
    }

    fn check(&self, grad: &wgpu::Buffer) -> GpuResult<()> {
        if grad.size() < self.bytes {
            return Err(GpuError::Input(format!(
                "gradient buffer of {} bytes for an MLP block of {}",
                grad.size(),
                self.bytes
            )));
        }
        Ok(())
    }

    /// Sets the MLP block of `grad` aside.
    pub fn encode_keep(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        grad: &wgpu::Buffer,
    ) -> GpuResult<()> {
        self.check(grad)?;
        encoder.copy_buffer_to_buffer(grad, 0, &self.kept, 0, self.bytes);
        self.any = true;
        Ok(())
    }

    /// The MLP gradient is what was kept in this step, or zero where nothing was.
    pub fn encode_restore(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        grad: &wgpu::Buffer,
    ) -> GpuResult<()> {
        self.check(grad)?;
        if self.any {
            encoder.copy_buffer_to_buffer(&self.kept, 0, grad, 0, self.bytes);
        } else {
            encoder.clear_buffer(grad, 0, Some(self.bytes));
        }
        self.any = false;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_context;
    use ngp::rng::Pcg32;
    use wgpu::util::DeviceExt;

    /// Sparse random gradients: most parameters zero, as a batch leaves a table.
    fn sparse(rng: &mut Pcg32, n: usize, density: f32) -> Vec<f32> {
        (0..n)
            .map(|_| {
                if rng.next_f32() < density {
                    rng.next_f32() - 0.5
                } else {
                    0.0
                }
            })
            .collect()
    }

    #[test]
    fn hold_back_matches_the_rule_by_hand_over_steps() {
        let Some(ctx) = test_context() else { return };
        held_steps(ctx, false);
        // With bounded entries (2 features an entry): their gate is always open.
        held_steps(ctx, true);
    }

    fn held_steps(ctx: &GpuContext, with_left: bool) {
        let (n, n_matrix) = (70_001usize, 1_001usize);
        let f = if with_left { 2 } else { 1 };
        let held = GpuHoldBack::new(ctx, n, n_matrix, f).unwrap();
        let mut brng = Pcg32::new(9, 3);
        let bounds: Vec<f32> = (0..(n - n_matrix) / f)
            .map(|_| match brng.next_f32() {
                r if with_left && r < 0.3 => r,
                _ => UNBOUNDED,
            })
            .collect();
        let left = TableBounds::from_bounds(bounds, f);
        held.upload_bounds(ctx, &left).unwrap();
        let grad = ctx
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("test gradient"),
                contents: bytemuck::cast_slice(&vec![0.0f32; n]),
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_SRC
                    | wgpu::BufferUsages::COPY_DST,
            });
        let mut rng = Pcg32::new(7, 1);
        let mut pending = vec![0.0f32; n - n_matrix];
        // Steps where the first scene opens the gate and another adds to it (a mixed step of
        // a cover and a hidden scene), where the other scene alone trains (the gate stays
        // closed), and the first alone.
        for (step, (cover_trained, hidden_trained)) in
            [(true, true), (false, true), (true, true), (true, false)]
                .into_iter()
                .enumerate()
        {
            let cover = if cover_trained {
                sparse(&mut rng, n, 0.2)
            } else {
                vec![0.0; n]
            };
            let hidden = if hidden_trained {
                sparse(&mut rng, n, 0.3)
            } else {
                vec![0.0; n]
            };
            ctx.queue
                .write_buffer(&grad, 0, bytemuck::cast_slice(&cover));
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            if cover_trained {
                held.encode_open_gate(ctx, &mut enc, &grad).unwrap();
            }
            ctx.queue.submit([enc.finish()]);
            ctx.wait().unwrap();
            let summed: Vec<f32> = cover.iter().zip(&hidden).map(|(c, h)| c + h).collect();
            ctx.queue
                .write_buffer(&grad, 0, bytemuck::cast_slice(&summed));
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            held.encode_hold_back(ctx, &mut enc, &grad).unwrap();
            ctx.queue.submit([enc.finish()]);
            let got: Vec<f32> = ctx.read_buffer(&grad, 4 * n as u64).unwrap();
            let mut want = summed.clone();
            for (j, (held, (w, c))) in pending
                .iter_mut()
                .zip(want[n_matrix..].iter_mut().zip(&cover[n_matrix..]))
                .enumerate()
            {
                if *c != 0.0 {
                    *w += std::mem::take(held);
                } else if !left.is_bounded(j / f) {
                    *held += *w;
                    *w = 0.0;
                }
            }
            assert_eq!(got, want, "step {step}: gradient");
            assert_eq!(
                held.pending(ctx).unwrap(),
                pending,
                "step {step}: held back"
            );
        }
        assert!(pending.iter().any(|&p| p != 0.0), "something was held back");

        // The clamp after Adam: the host's rule on the whole weight buffer.
        let mut weights: Vec<f32> = (0..n).map(|_| 2.0 * brng.next_f32() - 1.0).collect();
        let buf = ctx
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("test weights"),
                contents: bytemuck::cast_slice(&weights),
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            });
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        held.encode_clamp(ctx, &mut enc, &buf).unwrap();
        ctx.queue.submit([enc.finish()]);
        let got: Vec<f32> = ctx.read_buffer(&buf, 4 * n as u64).unwrap();
        let before = weights.clone();
        left.clamp(&mut weights[n_matrix..]);
        assert_eq!(got, weights, "clamped weights");
        assert_eq!(got != before, with_left, "the clamp moved a weight");
    }

    #[test]
    fn a_table_of_nothing_is_an_error() {
        let Some(ctx) = test_context() else { return };
        assert!(GpuHoldBack::new(ctx, 10, 10, 1).is_err());
        assert!(GpuHoldBack::new(ctx, 10, 11, 1).is_err());
        assert!(
            GpuHoldBack::new(ctx, 11, 2, 2).is_err(),
            "9 parameters in entries of 2"
        );
    }
}
