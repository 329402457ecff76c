//! The cover-paced table on the device (`pacing.wgsl`): the CPU trainer's
//! [`TrainConfig::cover_paced_table`](crate::ngp::train::TrainConfig::cover_paced_table)
//! for a gradient that lives in a GPU buffer. The CPU decides per worker partial which
//! entries the cover reached; here the summed gradient decides, which is the rule the
//! optimizer applies to a zero gradient on both backends.

use super::{
    GpuContext, GpuError, GpuResult, auto_layout_pipelines, buffer_entry as entry, check_binding,
    device_buffer,
};

use crate::ngp::train::left_entries::{LeftEntries, REACHED};

const PACING_WGSL: &str = include_str!("pacing.wgsl");
const WORKGROUP: u32 = 256;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct PacingParams {
    n_table: u32,
    n_matrix: u32,
    row_width: u32,
    n_features: u32,
}

/// The gate and the held-back gradients of the table parameters `n_matrix..n_params`.
pub struct GpuPacing {
    gate: wgpu::Buffer,
    pending: wgpu::Buffer,
    /// Per table entry: the bound of an entry the cover has left, or
    /// [`REACHED`](crate::ngp::train::left_entries::REACHED).
    bound: wgpu::Buffer,
    uniform: wgpu::Buffer,
    open: wgpu::ComputePipeline,
    hold: wgpu::ComputePipeline,
    clamp: wgpu::ComputePipeline,
    groups: [u32; 2],
    n_params: u32,
}

impl GpuPacing {
    pub fn new(
        ctx: &GpuContext,
        n_params: usize,
        n_matrix: usize,
        n_features: usize,
    ) -> GpuResult<GpuPacing> {
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
        let params = PacingParams {
            n_table,
            n_matrix: n_matrix as u32,
            row_width: gx * WORKGROUP,
            n_features: n_features as u32,
        };
        ctx.scoped("pacing kernels", || {
            let [open, hold, clamp] = auto_layout_pipelines(
                ctx,
                "pacing.wgsl",
                PACING_WGSL,
                ["open_gate", "hold_back", "clamp_left"],
            );
            let bound = device_buffer(ctx, "left entries' bounds", 4 * n_entries as u64);
            ctx.queue
                .write_buffer(&bound, 0, bytemuck::cast_slice(&vec![REACHED; n_entries]));
            let uniform = ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("pacing params"),
                size: std::mem::size_of::<PacingParams>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            ctx.queue
                .write_buffer(&uniform, 0, bytemuck::bytes_of(&params));
            GpuPacing {
                // Zeroed at creation (wgpu's guarantee): no gate open, nothing held.
                gate: device_buffer(ctx, "pacing gate", 4 * n_table as u64),
                pending: device_buffer(ctx, "pacing held-back gradients", 4 * n_table as u64),
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
        ctx.scoped("pacing", || {
            // Each pipeline's layout is derived from what its entry point uses: the gate
            // kernel has no held-back gradients.
            let mut entries = vec![entry(0, grad), entry(1, &self.gate)];
            if with_pending {
                entries.push(entry(2, &self.pending));
                entries.push(entry(4, &self.bound));
            }
            entries.push(entry(3, &self.uniform));
            let bind_group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("pacing"),
                layout: &pipeline.get_bind_group_layout(0),
                entries: &entries,
            });
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups(self.groups[0], self.groups[1], 1);
        })
    }

    /// After the cover's backward pass: opens the gate of every table parameter its
    /// gradient reached.
    pub fn encode_open_gate(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        grad: &wgpu::Buffer,
    ) -> GpuResult<()> {
        self.encode(ctx, encoder, &self.open, grad, false)
    }

    /// Before Adam: holds back the gradients the gate keeps out, releases the held-back
    /// gradients it lets through, and closes the gate.
    pub fn encode_hold_back(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        grad: &wgpu::Buffer,
    ) -> GpuResult<()> {
        self.encode(ctx, encoder, &self.hold, grad, true)
    }

    /// The bounds of the entries the cover has left ([`LeftEntries::bounds`]), after an
    /// update of its grid.
    pub fn upload_bounds(&self, ctx: &GpuContext, left: &LeftEntries) -> GpuResult<()> {
        let b = left.bounds();
        if 4 * b.len() as u64 != self.bound.size() {
            return Err(GpuError::Input(format!(
                "{} entry bounds for a buffer of {} bytes",
                b.len(),
                self.bound.size()
            )));
        }
        ctx.scoped("left entries' bounds", || {
            ctx.queue
                .write_buffer(&self.bound, 0, bytemuck::cast_slice(b))
        })
    }

    /// After Adam: holds every entry the cover has left within its bound.
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
        ctx.scoped("left entries' clamp", || {
            let bind_group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("left entries' clamp"),
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

    /// The held-back gradients, read back (for tests).
    pub fn pending(&self, ctx: &GpuContext) -> GpuResult<Vec<f32>> {
        ctx.read_buffer(&self.pending, self.pending.size())
    }
}

/// The MLP learnt from the cover alone on the device: the CPU trainer's
/// [`TrainConfig::cover_only_mlp`](crate::ngp::train::TrainConfig::cover_only_mlp). The
/// gradient's MLP block (its first `n_matrix` parameters) is copied aside after the cover's
/// backward pass and copied back before Adam, or cleared in a step without the cover.
pub struct GpuCoverMlp {
    kept: wgpu::Buffer,
    bytes: u64,
    cover_trained: bool,
}

impl GpuCoverMlp {
    pub fn new(ctx: &GpuContext, n_matrix: usize) -> GpuResult<GpuCoverMlp> {
        let bytes = 4 * n_matrix as u64;
        if bytes == 0 {
            return Err(GpuError::Input("an MLP of 0 parameters".into()));
        }
        check_binding(ctx, "the cover's MLP gradient", bytes)?;
        Ok(GpuCoverMlp {
            kept: ctx.scoped("cover MLP gradient", || {
                device_buffer(ctx, "cover MLP gradient", bytes)
            })?,
            bytes,
            cover_trained: false,
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

    /// After the cover's backward pass.
    pub fn encode_keep(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        grad: &wgpu::Buffer,
    ) -> GpuResult<()> {
        self.check(grad)?;
        encoder.copy_buffer_to_buffer(grad, 0, &self.kept, 0, self.bytes);
        self.cover_trained = true;
        Ok(())
    }

    /// Before Adam: the MLP gradient is the cover's, or zero in a step without it.
    pub fn encode_restore(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        grad: &wgpu::Buffer,
    ) -> GpuResult<()> {
        self.check(grad)?;
        if self.cover_trained {
            encoder.copy_buffer_to_buffer(&self.kept, 0, grad, 0, self.bytes);
        } else {
            encoder.clear_buffer(grad, 0, Some(self.bytes));
        }
        self.cover_trained = false;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gpu::test_context;
    use crate::ngp::train::left_entries::LeftEntries;
    use crate::rng::Pcg32;
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
    fn pacing_matches_the_rule_by_hand_over_steps() {
        let Some(ctx) = test_context() else { return };
        paced_steps(ctx, false);
        // With entries the cover left (2 features an entry): their gate is always open.
        paced_steps(ctx, true);
    }

    fn paced_steps(ctx: &GpuContext, with_left: bool) {
        let (n, n_matrix) = (70_001usize, 1_001usize);
        let f = if with_left { 2 } else { 1 };
        let pacing = GpuPacing::new(ctx, n, n_matrix, f).unwrap();
        let mut brng = Pcg32::new(9, 3);
        let bounds: Vec<f32> = (0..(n - n_matrix) / f)
            .map(|_| match brng.next_f32() {
                r if with_left && r < 0.3 => r,
                _ => REACHED,
            })
            .collect();
        let left = LeftEntries::from_bounds(bounds, f);
        pacing.upload_bounds(ctx, &left).unwrap();
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
        // Steps with the cover (mixed), without it (a random-scene step of a hidden scene),
        // and the cover alone.
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
                pacing.encode_open_gate(ctx, &mut enc, &grad).unwrap();
            }
            ctx.queue.submit([enc.finish()]);
            ctx.wait().unwrap();
            let summed: Vec<f32> = cover.iter().zip(&hidden).map(|(c, h)| c + h).collect();
            ctx.queue
                .write_buffer(&grad, 0, bytemuck::cast_slice(&summed));
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            pacing.encode_hold_back(ctx, &mut enc, &grad).unwrap();
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
                } else if !left.is_left(j / f) {
                    *held += *w;
                    *w = 0.0;
                }
            }
            assert_eq!(got, want, "step {step}: gradient");
            assert_eq!(
                pacing.pending(ctx).unwrap(),
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
        pacing.encode_clamp(ctx, &mut enc, &buf).unwrap();
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
        assert!(GpuPacing::new(ctx, 10, 10, 1).is_err());
        assert!(GpuPacing::new(ctx, 10, 11, 1).is_err());
        assert!(
            GpuPacing::new(ctx, 11, 2, 2).is_err(),
            "9 parameters in entries of 2"
        );
    }
}
