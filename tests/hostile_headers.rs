//! Headers that declare more than their file holds, run through the program under a 1 GiB
//! address-space limit: each must be refused with a message naming the file and the field
//! before anything is allocated for it (under the limit, such an allocation would abort
//! the process instead of failing cleanly).

use fuzz::mutate::png_chunk;
use std::path::Path;
use std::process::{Command, Output};
use testkit::cli::bin;

/// Runs `stegongp args` with its address space limited to 1 GiB (`ulimit -v`).
fn limited(args: &[&str]) -> Output {
    Command::new("sh")
        .arg("-c")
        .arg("ulimit -v 1048576 && exec \"$0\" \"$@\"")
        .arg(bin())
        .args(args)
        .output()
        .expect("run stegongp under sh")
}

/// A clean refusal: exit code 1 (not a signal, not an abort), a message with every needle.
fn refused(out: &Output, needles: &[&str]) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(
        out.status.code(),
        Some(1),
        "expected a clean error, got {:?}: {err}",
        out.status
    );
    for n in needles {
        assert!(err.contains(n), "message lacks '{n}': {err}");
    }
    assert!(!err.contains("panicked"), "{err}");
}

fn png_header(w: u32, h: u32) -> Vec<u8> {
    // Signature, an IHDR (8-bit RGB), one empty IDAT and IEND.
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend(w.to_be_bytes());
    ihdr.extend(h.to_be_bytes());
    ihdr.extend([8, 2, 0, 0, 0]);
    png_chunk(b"IHDR", &ihdr, &mut out);
    png_chunk(
        b"IDAT",
        &[0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01],
        &mut out,
    );
    png_chunk(b"IEND", &[], &mut out);
    out
}

/// A JPEG of `w`×`h` whose scan holds one block's bits: the header alone declares the size.
fn jpeg_header(w: u16, h: u16) -> Vec<u8> {
    let mut j = fuzz::seeds::jpeg_header(w, h);
    j.extend([0x3f, 0xff, 0xd9]);
    j
}

/// An instant-ngp dataset of two frames whose images are `image` (named `name`).
fn dataset_with_image(dir: &Path, name: &str, image: &[u8]) {
    std::fs::create_dir_all(dir).unwrap();
    let frames: Vec<_> = (0..2)
        .map(|i| serde_json::json!({"file_path": format!("{i}{name}"), "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,3],[0,0,0,1]]}))
        .collect();
    let t = serde_json::json!({"camera_angle_x": 0.7, "frames": frames});
    std::fs::write(dir.join("transforms.json"), t.to_string()).unwrap();
    for i in 0..2 {
        std::fs::write(dir.join(format!("{i}{name}")), image).unwrap();
    }
}

fn train(dir: &Path, out: &Path) -> Output {
    limited(&[
        "train",
        dir.to_str().unwrap(),
        "--steps",
        "1",
        "--device",
        "cpu",
        "--out",
        out.to_str().unwrap(),
    ])
}

#[test]
fn the_limit_lets_a_normal_command_run() {
    // Without this, every refusal below could be the limit's doing.
    let out = limited(&["--help"]);
    assert!(out.status.success(), "{out:?}");
}

#[test]
fn images_that_declare_65535_squared_pixels_are_refused() {
    let d = tempfile::tempdir().unwrap();
    let model = d.path().join("m.ingp");
    let png_dir = d.path().join("png");
    dataset_with_image(&png_dir, ".png", &png_header(65535, 65535));
    refused(&train(&png_dir, &model), &[".png", "IHDR", "65535x65535"]);
    let jpg_dir = d.path().join("jpg");
    dataset_with_image(&jpg_dir, ".jpg", &jpeg_header(65535, 65535));
    refused(&train(&jpg_dir, &model), &[".jpg", "SOF", "65535x65535"]);
    assert!(!model.exists(), "no model is written");
}

#[test]
fn snapshot_containers_larger_than_the_file_are_refused() {
    let d = tempfile::tempdir().unwrap();
    // {"params_binary": bin32 of 0xfffffff0 bytes}, three bytes present.
    let mut bin = vec![0x81, 0xad];
    bin.extend(b"params_binary");
    bin.extend([0xc6, 0xff, 0xff, 0xff, 0xf0, 1, 2, 3]);
    // {"snapshot": array32 of 2^32 − 1 elements}, none present.
    let mut arr = vec![0x81, 0xa8];
    arr.extend(b"snapshot");
    arr.extend([0xdd, 0xff, 0xff, 0xff, 0xff]);
    // {"snapshot": map32 of 2^32 − 1 pairs}.
    let mut map = vec![0x81, 0xa8];
    map.extend(b"snapshot");
    map.extend([0xdf, 0xff, 0xff, 0xff, 0xff]);
    for (name, bytes) in [
        ("bin.msgpack", bin),
        ("arr.msgpack", arr),
        ("map.msgpack", map),
    ] {
        let p = d.path().join(name);
        std::fs::write(&p, bytes).unwrap();
        refused(&limited(&["inspect", p.to_str().unwrap()]), &[name]);
    }
}

#[test]
fn capture_counts_larger_than_the_file_are_refused() {
    let d = tempfile::tempdir().unwrap();
    let model = d.path().join("m.ingp");
    // COLMAP: 2^62 cameras declared in a 20-byte cameras.bin.
    let colmap = d.path().join("colmap");
    std::fs::create_dir_all(colmap.join("sparse/0")).unwrap();
    std::fs::create_dir_all(colmap.join("images")).unwrap();
    let mut cams = (1u64 << 62).to_le_bytes().to_vec();
    cams.extend([0u8; 12]);
    std::fs::write(colmap.join("sparse/0/cameras.bin"), cams).unwrap();
    let mut imgs = (1u64 << 60).to_le_bytes().to_vec();
    imgs.extend([0u8; 12]);
    std::fs::write(colmap.join("sparse/0/images.bin"), imgs).unwrap();
    refused(
        &train(&colmap, &model),
        &["cameras.bin", "number of cameras"],
    );
    // LLFF: poses_bounds.npy declaring 2^40 rows of 17 float64.
    let llff = d.path().join("llff");
    std::fs::create_dir_all(llff.join("images")).unwrap();
    let dict = "{'descr': '<f8', 'fortran_order': False, 'shape': (1099511627776, 17), }";
    let mut header = dict.as_bytes().to_vec();
    while !(10 + header.len() + 1).is_multiple_of(64) {
        header.push(b' ');
    }
    header.push(b'\n');
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    npy.extend((header.len() as u16).to_le_bytes());
    npy.extend(header);
    npy.extend([0u8; 136]);
    std::fs::write(llff.join("poses_bounds.npy"), npy).unwrap();
    refused(&train(&llff, &model), &["poses_bounds.npy", "shape"]);
    assert!(!model.exists(), "no model is written");
}
