//! The wgpu compute backend (issue 10): device selection and the kernels, tested against
//! the CPU engine, which stays the oracle.
//!
//! Adapter policy: [`AdapterRequest::Auto`] takes a hardware GPU only; a software rasteriser
//! (Mesa's llvmpipe/lavapipe, SwiftShader: `DeviceType::Cpu`) runs only when asked for
//! ([`AdapterRequest::Software`], [`AdapterRequest::Any`]), because on a machine without a
//! GPU the CPU engine is faster than emulating one. CI has no GPU and tests on lavapipe.

pub mod compact;
pub mod count;
pub mod field;
pub mod fma;
pub mod grid;
pub mod held;
pub mod index;
pub mod loss;
pub mod mlp;
pub mod occupancy;
pub mod optimizer;
pub mod profile;
pub mod rays;
pub mod readback;
pub mod render;
pub mod renderer;
pub mod trainer;

pub use compact::{CompactInputs, Compacted};
pub use field::{DensityScratch, GpuField};
pub use grid::{GradAtomics, GridDispatch, GridEncoding, GridShape};
pub use index::{CornerBatch, CornerKernel, GpuIndex, GpuLevel, INDEX_WGSL, U64_WGSL};
pub use loss::{GpuRay, HostBatch, LossBuffers, LossConfig, LossKernel};
pub use mlp::{EncodedBatch, MLP_WGSL, MlpKernels, MlpWorkspace};
pub use occupancy::GpuOccupancy;
pub use optimizer::GpuOptimizer;
pub use rays::{GenRay, MarchedHost, RAYS_WGSL, RayBatch, RayKernels};
pub use render::{CompositeKernel, RayState, WaveSamples};
pub use renderer::{
    DensityProbe, GpuRenderer, RenderWaits, rebuild_occupancy_gpu, refine_occupancy_gpu,
};
pub use trainer::GpuTrainer;

use std::sync::OnceLock;
use std::sync::mpsc;
use wgpu::{DeviceType, Features};

/// Why the GPU backend cannot run, or what went wrong on the device.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error(
        "no GPU adapter found (wgpu looks for Vulkan and Metal devices; on Debian, Mesa's \
         software Vulkan driver is `apt-get install mesa-vulkan-drivers libvulkan1`)"
    )]
    NoAdapter,
    #[error(
        "no hardware GPU adapter, only software ones ({0}); the software adapter runs only \
         when asked for explicitly"
    )]
    OnlySoftware(String),
    #[error("no software adapter (llvmpipe/lavapipe); adapters found: {0}")]
    NoSoftware(String),
    #[error("{adapter}: cannot open a device: {err}")]
    RequestDevice {
        adapter: String,
        err: wgpu::RequestDeviceError,
    },
    #[error("GPU {what}: {msg}")]
    Device { what: &'static str, msg: String },
    #[error("GPU input: {0}")]
    Input(String),
}

pub type GpuResult<T> = std::result::Result<T, GpuError>;

/// Which adapter to open.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AdapterRequest {
    /// The best hardware GPU (discrete, then integrated, then virtual); never a software one.
    Auto,
    /// A software adapter (`DeviceType::Cpu`): tests and CI.
    Software,
    /// Hardware when there is one, software otherwise.
    Any,
}

impl std::str::FromStr for AdapterRequest {
    type Err = GpuError;

    /// `auto`, `software` or `any` (the benchmarks' adapter argument).
    fn from_str(s: &str) -> GpuResult<AdapterRequest> {
        match s {
            "auto" => Ok(AdapterRequest::Auto),
            "software" => Ok(AdapterRequest::Software),
            "any" => Ok(AdapterRequest::Any),
            _ => Err(GpuError::Input(format!(
                "adapter `{s}`: auto, software or any"
            ))),
        }
    }
}

/// What an adapter is and what the later kernels can count on.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct AdapterReport {
    pub name: String,
    pub backend: String,
    pub device_type: String,
    pub driver: String,
    pub software: bool,
    /// `SHADER_FLOAT32_ATOMIC`: the grid backward can accumulate with float atomics instead
    /// of compare-and-swap loops.
    pub float32_atomics: bool,
    pub f16: bool,
    pub subgroups: bool,
}

impl std::fmt::Display for AdapterReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let yn = |b: bool| if b { "yes" } else { "no" };
        write!(
            f,
            "{} ({}, {}, {}{}): f32 atomics {}, f16 {}, subgroups {}",
            self.name,
            self.backend,
            self.device_type,
            self.driver,
            if self.software { ", software" } else { "" },
            yn(self.float32_atomics),
            yn(self.f16),
            yn(self.subgroups)
        )
    }
}

/// One adapter wgpu finds, as `stegongp devices` lists it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct AdapterEntry {
    pub name: String,
    pub backend: String,
    pub device_type: String,
    pub driver: String,
    pub software: bool,
}

impl AdapterEntry {
    fn of(info: &wgpu::AdapterInfo) -> AdapterEntry {
        AdapterEntry {
            name: info.name.clone(),
            backend: format!("{:?}", info.backend),
            device_type: format!("{:?}", info.device_type),
            driver: [info.driver.as_str(), info.driver_info.as_str()]
                .iter()
                .filter(|s| !s.is_empty())
                .copied()
                .collect::<Vec<_>>()
                .join(" "),
            software: is_software(info),
        }
    }
}

/// A Vulkan (and Metal) instance and every adapter it finds, in wgpu's order.
fn enumerate() -> (wgpu::Instance, Vec<wgpu::Adapter>) {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = BACKENDS;
    let instance = wgpu::Instance::new(desc);
    let adapters = pollster::block_on(instance.enumerate_adapters(BACKENDS));
    (instance, adapters)
}

/// Every adapter present, as [`GpuContext::new`] chooses among them.
pub fn list_adapters() -> Vec<AdapterEntry> {
    enumerate()
        .1
        .iter()
        .map(|a| AdapterEntry::of(&a.get_info()))
        .collect()
}

/// An open device: what every kernel needs.
pub struct GpuContext {
    pub instance: wgpu::Instance,
    pub adapter: wgpu::Adapter,
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    report: AdapterReport,
    /// The [`fma::fma_is_fused`] probe's answer, once asked.
    fma_fused: OnceLock<bool>,
}

/// Software rasterisers report `DeviceType::Cpu`; the names catch a driver that reports
/// `Other` instead.
fn is_software(info: &wgpu::AdapterInfo) -> bool {
    let name = info.name.to_lowercase();
    info.device_type == DeviceType::Cpu
        || ["llvmpipe", "lavapipe", "swiftshader"]
            .iter()
            .any(|s| name.contains(s))
}

fn hardware_rank(t: DeviceType) -> u32 {
    match t {
        DeviceType::DiscreteGpu => 0,
        DeviceType::IntegratedGpu => 1,
        DeviceType::VirtualGpu => 2,
        DeviceType::Other | DeviceType::Cpu => 3,
    }
}

fn describe(adapters: &[wgpu::Adapter]) -> String {
    adapters
        .iter()
        .map(|a| {
            let i = a.get_info();
            format!("{} [{:?}, {:?}]", i.name, i.backend, i.device_type)
        })
        .collect::<Vec<_>>()
        .join("; ")
}

/// Picks an adapter by the module's policy from those present.
fn choose(adapters: Vec<wgpu::Adapter>, request: AdapterRequest) -> GpuResult<wgpu::Adapter> {
    if adapters.is_empty() {
        return Err(GpuError::NoAdapter);
    }
    let list = describe(&adapters);
    let (software, mut hardware): (Vec<_>, Vec<_>) = adapters
        .into_iter()
        .partition(|a| is_software(&a.get_info()));
    hardware.sort_by_key(|a| hardware_rank(a.get_info().device_type));
    let hw = hardware.into_iter().next();
    let sw = software.into_iter().next();
    match request {
        AdapterRequest::Auto => hw.ok_or(GpuError::OnlySoftware(list)),
        AdapterRequest::Software => sw.ok_or(GpuError::NoSoftware(list)),
        AdapterRequest::Any => hw.or(sw).ok_or(GpuError::NoAdapter),
    }
}

/// The backends the `gpu` feature builds (Metal only exists on Apple targets).
const BACKENDS: wgpu::Backends = wgpu::Backends::VULKAN.union(wgpu::Backends::METAL);

/// Features the kernels use when the adapter has them; none is required.
const WANTED: Features = Features::SHADER_FLOAT32_ATOMIC
    .union(Features::SHADER_F16)
    .union(Features::SUBGROUP)
    .union(Features::TIMESTAMP_QUERY)
    .union(Features::TIMESTAMP_QUERY_INSIDE_ENCODERS);

impl GpuContext {
    /// Opens a device on the adapter `request` picks (Vulkan and Metal adapters).
    pub fn new(request: AdapterRequest) -> GpuResult<GpuContext> {
        let (instance, adapters) = enumerate();
        let adapter = choose(adapters, request)?;
        let info = adapter.get_info();
        let features = adapter.features() & WANTED;
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("stegongp"),
            required_features: features,
            // The adapter's own limits: grid tables need storage bindings far past the
            // WebGPU defaults (128 MiB), which every desktop driver allows.
            required_limits: adapter.limits(),
            ..Default::default()
        }))
        .map_err(|err| GpuError::RequestDevice {
            adapter: info.name.clone(),
            err,
        })?;
        let entry = AdapterEntry::of(&info);
        let report = AdapterReport {
            name: entry.name,
            backend: entry.backend,
            device_type: entry.device_type,
            driver: entry.driver,
            software: entry.software,
            float32_atomics: features.contains(Features::SHADER_FLOAT32_ATOMIC),
            f16: features.contains(Features::SHADER_F16),
            subgroups: features.contains(Features::SUBGROUP),
        };
        Ok(GpuContext {
            instance,
            adapter,
            device,
            queue,
            report,
            fma_fused: OnceLock::new(),
        })
    }

    /// Opens the adapter a command-line word names (`auto`, `software`, `any`; none:
    /// `any`), as the benchmarks take it.
    pub fn from_arg(arg: Option<&str>) -> GpuResult<GpuContext> {
        GpuContext::new(arg.map_or(Ok(AdapterRequest::Any), str::parse)?)
    }

    pub fn report(&self) -> &AdapterReport {
        &self.report
    }

    /// Whether this adapter's `fma` rounds once, as the CPU's `mul_add` does
    /// ([`fma::fma_is_fused`], probed once a context).
    pub fn fma_fused(&self) -> GpuResult<bool> {
        if let Some(&f) = self.fma_fused.get() {
            return Ok(f);
        }
        let f = fma::fma_is_fused(self)?;
        Ok(*self.fma_fused.get_or_init(|| f))
    }

    /// The device's limits that bound what the kernels can do: batch sizes (storage
    /// bindings, buffers), workgroup shapes and shared memory, subgroup sizes.
    pub fn limits_report(&self) -> Vec<(&'static str, u64)> {
        let l = self.device.limits();
        let info = self.adapter.get_info();
        vec![
            ("subgroup_min_size", info.subgroup_min_size as u64),
            ("subgroup_max_size", info.subgroup_max_size as u64),
            (
                "max_storage_buffer_binding_size",
                l.max_storage_buffer_binding_size,
            ),
            ("max_buffer_size", l.max_buffer_size),
            (
                "max_storage_buffers_per_shader_stage",
                l.max_storage_buffers_per_shader_stage as u64,
            ),
            (
                "max_compute_workgroup_storage_size",
                l.max_compute_workgroup_storage_size as u64,
            ),
            (
                "max_compute_invocations_per_workgroup",
                l.max_compute_invocations_per_workgroup as u64,
            ),
            (
                "max_compute_workgroups_per_dimension",
                l.max_compute_workgroups_per_dimension as u64,
            ),
            (
                "max_compute_workgroup_size_x",
                l.max_compute_workgroup_size_x as u64,
            ),
        ]
    }

    /// Runs `f` with wgpu's validation and out-of-memory errors captured, so that a bad
    /// shader or an oversized buffer comes back as an error instead of wgpu's default
    /// panic.
    pub fn scoped<T>(&self, what: &'static str, f: impl FnOnce() -> T) -> GpuResult<T> {
        let scopes = [
            wgpu::ErrorFilter::Validation,
            wgpu::ErrorFilter::OutOfMemory,
            wgpu::ErrorFilter::Internal,
        ]
        .map(|filter| self.device.push_error_scope(filter));
        let out = f();
        // Scopes pop innermost first.
        let mut first = None;
        for scope in scopes.into_iter().rev() {
            if let Some(e) = pollster::block_on(scope.pop()) {
                first.get_or_insert(e);
            }
        }
        match first {
            Some(e) => Err(GpuError::Device {
                what,
                msg: e.to_string(),
            }),
            None => Ok(out),
        }
    }

    /// Waits until the queue is idle.
    pub fn wait(&self) -> GpuResult<()> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| GpuError::Device {
                what: "wait",
                msg: e.to_string(),
            })
    }

    /// Copies `bytes` bytes from the start of `src` (a `COPY_SRC` buffer) back to the host.
    pub fn read_buffer<T: bytemuck::Pod>(
        &self,
        src: &wgpu::Buffer,
        bytes: u64,
    ) -> GpuResult<Vec<T>> {
        let mut parts = self.read_buffers(&[(src, bytes)])?;
        Ok(bytemuck::pod_collect_to_vec(
            &parts.pop().unwrap_or_default(),
        ))
    }

    /// Reads back the first `bytes` of each of `parts` with one submission and one wait
    /// (where [`Self::read_buffer`] per buffer would wait once each).
    pub fn read_buffers(&self, parts: &[(&wgpu::Buffer, u64)]) -> GpuResult<Vec<Vec<u8>>> {
        const ALIGN: u64 = 256;
        let mut total = 0u64;
        let offsets: Vec<u64> = parts
            .iter()
            .map(|&(_, bytes)| {
                let at = total;
                total += bytes.div_ceil(ALIGN) * ALIGN;
                at
            })
            .collect();
        if total == 0 {
            return Ok(parts.iter().map(|_| Vec::new()).collect());
        }
        let staging = self.scoped("readback", || {
            let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("readback"),
                size: total,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            let mut enc = self.device.create_command_encoder(&Default::default());
            for (&(src, bytes), &o) in parts.iter().zip(&offsets) {
                if bytes > 0 {
                    enc.copy_buffer_to_buffer(src, 0, &staging, o, bytes);
                }
            }
            self.queue.submit([enc.finish()]);
            staging
        })?;
        let (tx, rx) = mpsc::channel();
        staging.map_async(wgpu::MapMode::Read, .., move |r| {
            // The receiver waits below; a send can only fail if it is gone.
            let _ = tx.send(r);
        });
        self.wait()?;
        let map_err = |msg: String| GpuError::Device {
            what: "readback",
            msg,
        };
        rx.recv()
            .map_err(|e| map_err(e.to_string()))?
            .map_err(|e| map_err(e.to_string()))?;
        let out = {
            let view = staging
                .get_mapped_range(..)
                .map_err(|e| map_err(e.to_string()))?;
            parts
                .iter()
                .zip(&offsets)
                .map(|(&(_, bytes), &o)| view[o as usize..(o + bytes) as usize].to_vec())
                .collect()
        };
        staging.unmap();
        Ok(out)
    }
}

/// A storage buffer of `bytes` (at least 16: a binding cannot be empty) that can also be
/// copied to and from; wgpu zero-initialises it.
pub(crate) fn device_buffer(ctx: &GpuContext, label: &str, bytes: u64) -> wgpu::Buffer {
    ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: bytes.max(16),
        usage: wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::COPY_SRC
            | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

/// Compiles `source` once and makes one pipeline per entry point, each with the bind-group
/// layout wgpu derives from the shader (kernels whose bind groups are built per pipeline).
/// Call inside [`GpuContext::scoped`].
pub(crate) fn auto_layout_pipelines<const N: usize>(
    ctx: &GpuContext,
    label: &str,
    source: &str,
    entries: [&str; N],
) -> [wgpu::ComputePipeline; N] {
    let module = ctx
        .device
        .create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(label),
            source: wgpu::ShaderSource::Wgsl(source.into()),
        });
    pipelines_of(ctx, &module, entries)
}

/// [`auto_layout_pipelines`] of a module compiled without naga's runtime checks (index
/// clamping, loop bounding), which keep a driver's compiler from unrolling loops and from
/// keeping small arrays in registers.
///
/// # Safety
/// Every index the source computes into a buffer, a workgroup array or a private array must
/// be in bounds for every input the caller lets through, and every loop must end.
pub(crate) unsafe fn unchecked_auto_layout_pipelines<const N: usize>(
    ctx: &GpuContext,
    label: &str,
    source: &str,
    entries: [&str; N],
) -> [wgpu::ComputePipeline; N] {
    let desc = wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(source.into()),
    };
    // SAFETY: the caller's contract.
    let module = unsafe {
        ctx.device
            .create_shader_module_trusted(desc, wgpu::ShaderRuntimeChecks::unchecked())
    };
    pipelines_of(ctx, &module, entries)
}

fn pipelines_of<const N: usize>(
    ctx: &GpuContext,
    module: &wgpu::ShaderModule,
    entries: [&str; N],
) -> [wgpu::ComputePipeline; N] {
    let d = &ctx.device;
    entries.map(|entry| {
        d.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(entry),
            layout: None,
            module,
            entry_point: Some(entry),
            compilation_options: Default::default(),
            cache: None,
        })
    })
}

/// Entry points of one WGSL module that share one explicit bind-group layout: storage
/// buffers at bindings `0..n_storage` (read-only where `read_only(binding)`), then one
/// uniform at binding `n_storage` (with a dynamic offset if asked). Returns the layout and
/// the pipelines in the order of `entries`. Call inside [`GpuContext::scoped`].
pub(crate) fn shared_layout_pipelines(
    ctx: &GpuContext,
    label: &str,
    source: &str,
    n_storage: u32,
    read_only: impl Fn(u32) -> bool,
    dynamic_uniform: bool,
    entries: &[&str],
) -> (wgpu::BindGroupLayout, Vec<wgpu::ComputePipeline>) {
    let d = &ctx.device;
    let module = d.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(source.into()),
    });
    let buffer = |binding, ty, has_dynamic_offset| wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty,
            has_dynamic_offset,
            min_binding_size: None,
        },
        count: None,
    };
    let mut layout_entries: Vec<_> = (0..n_storage)
        .map(|b| {
            let ty = wgpu::BufferBindingType::Storage {
                read_only: read_only(b),
            };
            buffer(b, ty, false)
        })
        .collect();
    layout_entries.push(buffer(
        n_storage,
        wgpu::BufferBindingType::Uniform,
        dynamic_uniform,
    ));
    let layout = d.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some(label),
        entries: &layout_entries,
    });
    let pl = d.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some(label),
        bind_group_layouts: &[Some(&layout)],
        immediate_size: 0,
    });
    let pipelines = entries
        .iter()
        .map(|entry| {
            d.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: Some(&pl),
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        })
        .collect();
    (layout, pipelines)
}

/// That a storage binding of `bytes` fits the device (its binding and buffer limits).
pub(crate) fn check_binding(ctx: &GpuContext, what: &str, bytes: u64) -> GpuResult<()> {
    let limits = ctx.device.limits();
    let max = limits
        .max_storage_buffer_binding_size
        .min(limits.max_buffer_size);
    if bytes > max {
        return Err(GpuError::Input(format!(
            "{what}: {bytes} bytes, past the device's {max}-byte storage binding"
        )));
    }
    Ok(())
}

/// A whole buffer bound at `binding`.
pub(crate) fn buffer_entry(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: buffer.as_entire_binding(),
    }
}

/// The device GPU tests run on: hardware if present, else the software adapter. `None`
/// (with a message) only where no adapter exists at all; with `CI=true` in the environment
/// a missing adapter fails the test instead, so CI cannot pass by skipping.
///
/// One context per test process, shared by its tests (opening a device costs more than
/// most kernel tests).
pub fn test_context() -> Option<&'static GpuContext> {
    static CTX: OnceLock<Option<GpuContext>> = OnceLock::new();
    CTX.get_or_init(|| match GpuContext::new(AdapterRequest::Any) {
        Ok(ctx) => {
            eprintln!("GPU tests on {}", ctx.report());
            Some(ctx)
        }
        Err(e @ GpuError::NoAdapter) => {
            let ci = std::env::var("CI").is_ok_and(|v| v == "true");
            assert!(
                !ci,
                "CI=true and {e}: the GPU tests must run in CI (.ci/run installs it)"
            );
            eprintln!("skipping GPU test: {e}");
            None
        }
        Err(e) => panic!("a GPU adapter exists but cannot be used: {e}"),
    })
    .as_ref()
}

impl From<GpuError> for ngp::Error {
    fn from(e: GpuError) -> Self {
        ngp::Error::Other(e.to_string())
    }
}

impl ngp::train::TrainBackend for GpuTrainer<'_> {
    fn train_step(&mut self) -> ngp::Result<ngp::train::StepStats> {
        Ok(GpuTrainer::train_step(self)?)
    }
    fn step(&self) -> u32 {
        self.step
    }
    fn n_scenes(&self) -> usize {
        GpuTrainer::n_scenes(self)
    }
    fn dataset(&self, i: usize) -> &ngp::data::Dataset {
        GpuTrainer::dataset(self, i)
    }
    fn set_policy(&mut self, policy: Box<dyn ngp::train::TrainPolicy>) -> ngp::Result<()> {
        Ok(GpuTrainer::set_policy(self, policy)?)
    }
    fn model(&self, loss: f32) -> ngp::Result<ngp::model::Model> {
        Ok(GpuTrainer::model(self, loss)?)
    }
    fn save_state(&self) -> ngp::Result<ngp::train::state::Value> {
        GpuTrainer::save_state_doc(self)
    }
    fn restore_state(
        &mut self,
        doc: &ngp::train::state::Value,
        origin: &std::path::Path,
    ) -> ngp::Result<()> {
        GpuTrainer::restore_state_doc(self, doc, origin)
    }
    fn flush_stats(&mut self) -> ngp::Result<ngp::train::StepStats> {
        Ok(GpuTrainer::flush_stats(self)?)
    }
    fn profile_device(&mut self, every: u32) -> bool {
        GpuTrainer::profile_device(self, every)
    }
    fn half_grid(&mut self) -> ngp::Result<()> {
        Ok(GpuTrainer::set_half_grid(self, true)?)
    }
    fn device_profile(&self) -> Vec<(String, f64)> {
        GpuTrainer::device_profile(self)
    }
}

impl ngp::render::RenderBackend for GpuRenderer<'_> {
    fn render(
        &mut self,
        cam: &ngp::camera::Camera,
        opts: &ngp::render::image::RenderOptions,
    ) -> ngp::Result<ngp::render::image::RenderedImage> {
        Ok(GpuRenderer::render(self, cam, opts)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_never_takes_a_software_adapter() {
        let Some(ctx) = test_context() else { return };
        let r = GpuContext::new(AdapterRequest::Auto);
        if ctx.report().software {
            // Whatever Auto picks, it is not the software adapter we test on.
            match r {
                Ok(hw) => assert!(!hw.report().software, "{}", hw.report()),
                Err(e) => assert!(matches!(e, GpuError::OnlySoftware(_)), "{e}"),
            }
        }
    }

    #[test]
    fn adapter_words_parse_and_others_are_refused() {
        assert_eq!(
            "auto".parse::<AdapterRequest>().unwrap(),
            AdapterRequest::Auto
        );
        assert_eq!(
            "software".parse::<AdapterRequest>().unwrap(),
            AdapterRequest::Software
        );
        assert_eq!(
            "any".parse::<AdapterRequest>().unwrap(),
            AdapterRequest::Any
        );
        assert!(matches!(
            "gpu".parse::<AdapterRequest>(),
            Err(GpuError::Input(_))
        ));
    }

    #[test]
    fn report_names_the_adapter() {
        let Some(ctx) = test_context() else { return };
        let line = ctx.report().to_string();
        assert!(line.contains(&ctx.report().name) && line.contains("f32 atomics"));
        assert!(!ctx.report().backend.is_empty());
    }

    #[test]
    fn a_bad_shader_is_an_error_not_a_panic() {
        let Some(ctx) = test_context() else { return };
        let r = ctx.scoped("shader", || {
            ctx.device
                .create_shader_module(wgpu::ShaderModuleDescriptor {
                    label: None,
                    source: wgpu::ShaderSource::Wgsl("fn main( {".into()),
                })
        });
        assert!(matches!(r, Err(GpuError::Device { .. })));
    }
}
