//! `stegongp devices`: the GPU adapters this machine has, the one `--device gpu` opens, and
//! its limits; `--require-hardware` makes a script fail loudly where only a software
//! adapter (llvmpipe) or none is found, before it measures the wrong thing.

use anyhow::{Result, bail};
use serde::Serialize;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Exit with an error unless `--device gpu` would open a hardware GPU.
    #[arg(long)]
    pub require_hardware: bool,
    /// Print a JSON report on stdout.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct Adapter {
    name: String,
    backend: String,
    device_type: String,
    driver: String,
    software: bool,
}

#[derive(Serialize)]
struct Opened {
    adapter: String,
    software: bool,
    float32_atomics: bool,
    f16: bool,
    subgroups: bool,
    /// The adapter's fma rounds once, as the CPU's (the grid then picks cells with it
    /// rather than an exact integer emulation); null where the probe could not run.
    fma_fused: Option<bool>,
    limits: std::collections::BTreeMap<&'static str, u64>,
}

#[derive(Serialize)]
struct Report {
    adapters: Vec<Adapter>,
    /// What `--device gpu` opens; null where it cannot open any.
    opened: Option<Opened>,
    /// Why no adapter could be opened.
    #[serde(skip_serializing_if = "Option::is_none")]
    error: Option<String>,
}

#[cfg(feature = "gpu")]
fn report() -> Report {
    use stegongp::gpu::{AdapterRequest, GpuContext, list_adapters};
    let adapters = list_adapters()
        .into_iter()
        .map(|a| Adapter {
            name: a.name,
            backend: a.backend,
            device_type: a.device_type,
            driver: a.driver,
            software: a.software,
        })
        .collect();
    match GpuContext::new(AdapterRequest::Any) {
        Ok(ctx) => {
            let r = ctx.report();
            Report {
                adapters,
                opened: Some(Opened {
                    adapter: r.to_string(),
                    software: r.software,
                    float32_atomics: r.float32_atomics,
                    f16: r.f16,
                    subgroups: r.subgroups,
                    fma_fused: ctx.fma_fused().ok(),
                    limits: ctx.limits_report().into_iter().collect(),
                }),
                error: None,
            }
        }
        Err(e) => Report {
            adapters,
            opened: None,
            error: Some(e.to_string()),
        },
    }
}

#[cfg(not(feature = "gpu"))]
fn report() -> Report {
    Report {
        adapters: Vec::new(),
        opened: None,
        error: Some("this build has no GPU backend (the `gpu` feature)".into()),
    }
}

pub fn run(a: Args) -> Result<()> {
    let r = report();
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        if r.adapters.is_empty() {
            println!("no GPU adapter found");
        }
        for ad in &r.adapters {
            println!(
                "adapter: {} [{}, {}] {}{}",
                ad.name,
                ad.backend,
                ad.device_type,
                ad.driver,
                if ad.software { " (software)" } else { "" }
            );
        }
        match &r.opened {
            Some(o) => {
                println!("--device gpu opens: {}", o.adapter);
                if let Some(f) = o.fma_fused {
                    println!(
                        "  fma: {}",
                        if f {
                            "fused (grid cells from the hardware's fma)"
                        } else {
                            "rounds twice (grid cells from the exact emulation)"
                        }
                    );
                }
                for (k, v) in &o.limits {
                    println!("  {k}: {v}");
                }
            }
            None => println!(
                "--device gpu opens nothing: {}",
                r.error.as_deref().unwrap_or("")
            ),
        }
    }
    if a.require_hardware {
        match &r.opened {
            Some(o) if !o.software => {}
            Some(o) => bail!(
                "--require-hardware: only a software adapter was found ({}); no hardware GPU \
                 to measure (is the vendor's Vulkan driver installed and its ICD visible?)",
                o.adapter
            ),
            None => bail!(
                "--require-hardware: no GPU adapter could be opened: {}",
                r.error.as_deref().unwrap_or("none found")
            ),
        }
    }
    Ok(())
}
