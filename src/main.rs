//! The `stegongp` command-line program: one module per subcommand under `cli/`.

mod cli;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "stegongp",
    version,
    about = "Hide 3D scenes in Instant-NGP models behind a secret key"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Ray-trace a generated scene into the NeRF-synthetic format.
    Synth(cli::synth::Args),
    /// Train a model (plain, or cover + hidden scenes with keys).
    Train(cli::train::Args),
    /// Render a dataset's cameras with a model (the cover, or a hidden scene with --key).
    Render(cli::render::Args),
    /// PSNR / SSIM of a model on a dataset's held-out views.
    Eval(cli::eval::Args),
    /// Describe a model file.
    Inspect(cli::inspect::Args),
    /// Make a key file.
    Keygen(cli::keygen::Args),
    /// The whole story on generated scenes, no downloads.
    Demo(cli::demo::Args),
    /// Run one of the paper's experiments and write a report.
    Experiment(cli::experiment::Args),
    /// Write a COLMAP or LLFF capture as an instant-ngp transforms.json.
    Convert(cli::convert::Args),
    /// A phone video or a folder of photos to a posed capture that `train` reads (ffmpeg,
    /// then COLMAP's features, matching and mapper).
    Process(cli::process::Args),
    /// Steganalysis: statistics of a model file that could betray a hidden scene, and a score.
    Detect(cli::detect::Args),
    /// Render a camera path (orbit, spiral, or a nerfstudio / instant-ngp path file) to an
    /// MP4 or PNG frames: the cover, a hidden scene with its key, or both beside a wrong key.
    Video(cli::video::Args),
    /// A local web viewer: orbit the cover, enter a key to see the hidden scene, record a
    /// camera path for `video`.
    View(cli::view::Args),
    /// The GPU adapters found, the one `--device gpu` opens and its limits.
    Devices(cli::devices::Args),
    /// The surface of the cover (or with --key of a hidden scene) as a coloured PLY or OBJ
    /// mesh, by marching cubes on the network's density.
    Mesh(cli::mesh::Args),
    /// Edit a model as whoever downloads it might (noise, pruning, quantisation,
    /// fine-tuning, purification, re-distillation) and write the result as a snapshot: what
    /// a hidden scene survives.
    Attack(cli::attack::Args),
}

/// Mesa's device-select Vulkan layer, which the loader runs in every program that opens
/// Vulkan, looks for a desktop session to pick the default GPU, and without one (a server,
/// a container, CI) prints "error: XDG_RUNTIME_DIR is invalid or not set" while `--device
/// auto` merely probes. With no session there is nothing for it to select by, so it is
/// turned off by its own switch, unless the user set that switch or asked the layer for a
/// device.
fn quiet_device_select() {
    let unset = |k: &str| std::env::var_os(k).is_none();
    if unset("XDG_RUNTIME_DIR") && unset("NODEVICE_SELECT") && unset("MESA_VK_DEVICE_SELECT") {
        // SAFETY: no other thread exists yet to read the environment.
        unsafe { std::env::set_var("NODEVICE_SELECT", "1") };
    }
}

fn main() {
    // Rust ignores SIGPIPE, which turns a closed pipe (`stegongp detect M | head`) into a
    // panic in println!; a command-line tool should end quietly, as others do.
    #[cfg(unix)]
    // SAFETY: setting a signal's disposition to its default, before any thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    quiet_device_select();
    let cli = Cli::parse();
    let result = match cli.cmd {
        Cmd::Synth(a) => cli::synth::run(a),
        Cmd::Train(a) => cli::train::run(a),
        Cmd::Render(a) => cli::render::run(a),
        Cmd::Eval(a) => cli::eval::run(a),
        Cmd::Inspect(a) => cli::inspect::run(a),
        Cmd::Keygen(a) => cli::keygen::run(a),
        Cmd::Demo(a) => cli::demo::run(a),
        Cmd::Experiment(a) => cli::experiment::run(a),
        Cmd::Convert(a) => cli::convert::run(a),
        Cmd::Process(a) => cli::process::run(a),
        Cmd::Detect(a) => cli::detect::run(a),
        Cmd::Video(a) => cli::video::run(a),
        Cmd::View(a) => cli::view::run(a),
        Cmd::Devices(a) => cli::devices::run(a),
        Cmd::Mesh(a) => cli::mesh::run(a),
        Cmd::Attack(a) => cli::attack::run(a),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

#[cfg(test)]
mod tests {
    use clap::CommandFactory;

    /// clap's own consistency checks of every subcommand (defaults that parse, names that
    /// don't clash), which it otherwise makes only when a subcommand runs.
    #[test]
    fn cli_definition_is_consistent() {
        super::Cli::command().debug_assert();
    }
}
