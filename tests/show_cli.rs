//! Seeing the scenes: camera-path files, `stegongp video` (MP4 read back with the codec's own
//! decoder, frames against `render`'s), and `stegongp view` driven in a real browser
//! (Debian's Chromium, headless, through the DevTools protocol).
// A test reads as one story; the 120-line limit (clippy.toml) is the program's.
#![allow(clippy::too_many_lines)]

use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::OnceLock;
use std::time::Duration;
use stegongp::viewer::frame::Rgb8;
use stegongp::viewer::video::decode_mp4;
use testkit::browser::{Browser, decode_base64, find_chromium};
use testkit::cli::{bin, fails_naming, ok, stdout_ok, stegongp};

/// A cover object and a hidden text scene in one model, trained on the CPU (≈ 30 s), with
/// its key.
struct Fixture {
    dir: PathBuf,
}

impl Fixture {
    fn p(&self, name: &str) -> String {
        self.dir.join(name).to_str().unwrap().to_string()
    }
}

fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap().keep();
        let f = Fixture { dir };
        // The cover at 96 px, trained at half that: its renders are smooth enough that
        // H.264's 4:2:0 chroma alone costs less than the 35 dB a video frame must keep
        // (a 48-px render of this textured object loses 33 dB to 4:2:0 before any codec).
        for (scene, out, res) in [("object", "cover", "96"), ("text", "text", "48")] {
            ok(&stegongp(&[
                "synth",
                "--scene",
                scene,
                "--res",
                res,
                "--train",
                "24",
                "--test",
                "2",
                "--out",
                &f.p(out),
            ]));
        }
        // A key from a passphrase and salt: the same model on every run.
        let mut keygen = Command::new(bin())
            .args([
                "keygen",
                "--passphrase",
                "--salt",
                "show-cli-fixture",
                "--out",
                &f.p("k.json"),
            ])
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        keygen
            .stdin
            .take()
            .unwrap()
            .write_all(b"the fixture's passphrase\n")
            .unwrap();
        let out = keygen.wait_with_output().unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        ok(&stegongp(&[
            "train",
            &f.p("cover"),
            "--downscale",
            "2",
            "--hidden",
            &f.p("text"),
            "--key",
            &f.p("k.json"),
            "--steps",
            "200",
            "--batch",
            "8192",
            "--log2-t",
            "15",
            "--out",
            &f.p("m.ingp"),
        ]));
        f
    })
}

fn load_png(path: &Path) -> Rgb8 {
    Rgb8::load_png(path).unwrap_or_else(|e| panic!("{e}"))
}

/// nerfstudio's camera_path.json for a NeRF-synthetic split's first `n` cameras (their
/// transform_matrix and camera_angle_x, square images), as nerfstudio's viewer writes one.
fn nerfstudio_path_of(transforms: &Path, n: usize, size: u32) -> serde_json::Value {
    let t: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(transforms).unwrap()).unwrap();
    let fov = t["camera_angle_x"].as_f64().unwrap().to_degrees();
    let cams: Vec<_> = t["frames"].as_array().unwrap()[..n]
        .iter()
        .map(|f| {
            let m: Vec<f64> = f["transform_matrix"]
                .as_array()
                .unwrap()
                .iter()
                .flat_map(|row| row.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()))
                .collect();
            serde_json::json!({"camera_to_world": m, "fov": fov, "aspect": 1.0})
        })
        .collect();
    serde_json::json!({
        "camera_type": "perspective", "render_width": size, "render_height": size, "fps": 10,
        "seconds": n as f64 / 10.0, "camera_path": cams,
    })
}

#[test]
fn video_frames_match_render_of_the_same_cameras() {
    let f = fixture();
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    // The cover's two test cameras as a nerfstudio path: its poses go through the nerf → ngp
    // frame as `render`'s dataset loader takes them.
    let path = nerfstudio_path_of(&f.dir.join("cover/transforms_test.json"), 2, 96);
    std::fs::write(p("cp.json"), path.to_string()).unwrap();
    ok(&stegongp(&[
        "video",
        "--model",
        &f.p("m.ingp"),
        "--path",
        &p("cp.json"),
        "--out",
        &p("v.mp4"),
        "--frames-dir",
        &p("frames"),
    ]));
    ok(&stegongp(&[
        "render",
        "--model",
        &f.p("m.ingp"),
        "--data",
        &f.p("cover"),
        "--out",
        &p("render"),
    ]));
    let video = decode_mp4(Path::new(&p("v.mp4"))).unwrap();
    assert_eq!((video.width, video.height, video.frames.len()), (96, 96, 2));
    assert!((video.fps - 10.0).abs() < 1e-6, "{}", video.fps);
    for i in 0..2 {
        let rendered = load_png(&d.path().join(format!("render/rgb_{i:03}.png")));
        let png = load_png(&d.path().join(format!("frames/frame_{i:05}.png")));
        // The same renderer on the same camera, reached through the path file.
        let exact = png.psnr(&rendered);
        assert!(
            exact > 45.0,
            "frame {i}: PNG frame {exact:.1} dB from render's"
        );
        // 4:2:0 video keeps one chroma sample per 2×2 pixels: on this textured object that
        // alone costs more than 35 dB would allow, so the codec is held to 35 dB or to
        // within 1.5 dB of what 4:2:0 without any compression keeps, whichever is lower.
        let bound = rendered.chroma_420_psnr();
        let decoded = video.frames[i].psnr(&rendered);
        eprintln!(
            "frame {i}: decoded MP4 {decoded:.2} dB from render's; 4:2:0 alone {bound:.2} dB"
        );
        assert!(
            decoded >= 35f64.min(bound - 1.5),
            "frame {i}: decoded MP4 frame {decoded:.1} dB from render's (4:2:0 alone: {bound:.1} dB)"
        );
    }
}

/// As instant-ngp: `render` (like its screenshots, videos and viewer) stops rays at 0.01
/// unless told otherwise, `eval` (like its run.py on test views) at 1e-4.
#[test]
fn render_stops_rays_where_the_viewer_does_and_eval_where_scoring_does() {
    let f = fixture();
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    let base = [
        "--model",
        &f.p("m.ingp"),
        "--data",
        &f.p("cover"),
        "--views",
        "1",
    ];
    let render = |out: &str, t: Option<&str>| {
        let mut args = vec!["render"];
        args.extend(base);
        args.extend(["--out", out]);
        if let Some(t) = t {
            args.extend(["--min-transmittance", t]);
        }
        ok(&stegongp(&args));
    };
    render(&p("default"), None);
    render(&p("viewing"), Some("0.01"));
    render(&p("scoring"), Some("0.0001"));
    let bytes = |dir: &str, name: &str| std::fs::read(d.path().join(dir).join(name)).unwrap();
    for name in ["rgb_000.png", "depth_000.png", "opacity_000.png"] {
        assert!(
            bytes("default", name) == bytes("viewing", name),
            "{name}: render's default is not --min-transmittance 0.01"
        );
    }
    // Rays through the object stop with T just under 0.01 at 0.01 (opacity ~0.99, 8-bit
    // 252–254) and under 1e-4 at 1e-4 (255): the opacities tell the two apart.
    assert!(
        bytes("default", "opacity_000.png") != bytes("scoring", "opacity_000.png"),
        "render's default stops rays where 1e-4 does"
    );
    let samples = |t: Option<&str>| {
        let mut args = vec!["eval"];
        args.extend(base);
        args.extend(["--no-lpips", "--json"]);
        if let Some(t) = t {
            args.extend(["--min-transmittance", t]);
        }
        let v: serde_json::Value = serde_json::from_str(&stdout_ok(&stegongp(&args))).unwrap();
        v["views"][0]["samples_per_ray"].as_f64().unwrap()
    };
    let (default, scoring, viewing) = (
        samples(None),
        samples(Some("0.0001")),
        samples(Some("0.01")),
    );
    assert_eq!(
        default, scoring,
        "eval's default is not --min-transmittance 1e-4"
    );
    assert!(
        viewing < scoring,
        "0.01 evaluates {viewing} samples a ray, 1e-4 {scoring}"
    );
}

#[test]
fn video_orbit_has_the_asked_frames_size_and_rate_and_its_path_round_trips() {
    let f = fixture();
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    let out = stegongp(&[
        "video",
        "--model",
        &f.p("m.ingp"),
        "--data",
        &f.p("cover"),
        "--path",
        "orbit",
        "--frames",
        "6",
        "--width",
        "40",
        "--height",
        "30",
        "--fps",
        "12",
        "--out",
        &p("o.mp4"),
        "--frames-dir",
        &p("o"),
        "--write-path",
        &p("orbit.json"),
        "--json",
    ]);
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    ok(&out);
    assert_eq!(report["frames"], 6);
    assert!(report["encode_seconds_per_frame"].as_f64().unwrap() > 0.0);
    let v = decode_mp4(Path::new(&p("o.mp4"))).unwrap();
    assert_eq!((v.width, v.height, v.frames.len()), (40, 30, 6));
    assert!((v.fps - 12.0).abs() < 1e-6);
    // Orbiting changes the view; every frame shows the object (not the white background).
    let frames: Vec<Rgb8> = (0..6)
        .map(|i| load_png(&d.path().join(format!("o/frame_{i:05}.png"))))
        .collect();
    assert!(frames[0].psnr(&frames[3]) < 30.0);
    let white = Rgb8::new(40, 30, [255; 3]);
    for fr in &frames {
        assert!(fr.psnr(&white) < 25.0, "a frame of background only");
    }
    // The path written is nerfstudio's format; rendering it again gives the same frames.
    ok(&stegongp(&[
        "video",
        "--model",
        &f.p("m.ingp"),
        "--data",
        &f.p("cover"),
        "--path",
        &p("orbit.json"),
        "--frames-dir",
        &p("again"),
    ]));
    for (i, fr) in frames.iter().enumerate() {
        let again = load_png(&d.path().join(format!("again/frame_{i:05}.png")));
        assert!(
            again.psnr(fr) > 45.0,
            "frame {i} differs after the round trip"
        );
    }
}

#[test]
fn side_by_side_shows_cover_key_and_wrong_key() {
    let f = fixture();
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    let common = [
        "--model",
        &f.p("m.ingp"),
        "--frames",
        "2",
        "--width",
        "32",
        "--height",
        "32",
    ];
    let mut args = vec!["video"];
    args.extend(common);
    let (key, sbs, sbs_mp4) = (f.p("k.json"), p("sbs"), p("sbs.mp4"));
    args.extend([
        "--side-by-side",
        "--key",
        &key,
        "--frames-dir",
        &sbs,
        "--out",
        &sbs_mp4,
    ]);
    ok(&stegongp(&args));
    for (key, dir) in [(None, "cover"), (Some(f.p("k.json")), "key")] {
        let mut a = vec!["video".to_string()];
        a.extend(common.iter().map(|s| s.to_string()));
        a.extend(["--frames-dir".into(), p(dir)]);
        if let Some(k) = key {
            a.extend(["--key".into(), k]);
        }
        let a: Vec<&str> = a.iter().map(String::as_str).collect();
        ok(&stegongp(&a));
    }
    let sbs = load_png(&d.path().join("sbs/frame_00001.png"));
    // Three 32-px panels and two 4-px gaps.
    assert_eq!((sbs.width, sbs.height), (104, 32));
    let cover = load_png(&d.path().join("cover/frame_00001.png"));
    let key = load_png(&d.path().join("key/frame_00001.png"));
    let panel = |i: u32| sbs.crop(i * 36, 12, 32, 20);
    // Below the labels, the panels are the single renders.
    assert_eq!(panel(0), cover.crop(0, 12, 32, 20));
    assert_eq!(panel(1), key.crop(0, 12, 32, 20));
    assert!(
        panel(2).psnr(&key.crop(0, 12, 32, 20)) < 25.0,
        "the wrong key shows the hidden scene"
    );
    assert!(
        panel(2).psnr(&cover.crop(0, 12, 32, 20)) < 25.0,
        "the wrong key shows the cover"
    );
    // Each panel carries a label: white letters on black in its top-left corner.
    for i in 0..3 {
        let top = sbs.crop(i * 36, 0, 32, 10);
        let px: Vec<&[u8]> = top.data.chunks(3).collect();
        assert!(
            px.iter().any(|p| *p == [255, 255, 255]) && px.iter().any(|p| *p == [0, 0, 0]),
            "panel {i} label"
        );
    }
    let v = decode_mp4(Path::new(&p("sbs.mp4"))).unwrap();
    assert_eq!((v.width, v.height, v.frames.len()), (104, 32, 2));
}

#[test]
fn video_refuses_bad_paths_and_options_clearly() {
    let f = fixture();
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    std::fs::write(
        p("bad.json"),
        r#"{"camera_path":[{"camera_to_world":[1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1], "fov":60},
                           {"camera_to_world":[1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]}]}"#,
    )
    .unwrap();
    let m = f.p("m.ingp");
    fails_naming(
        &stegongp(&[
            "video",
            "--model",
            &m,
            "--path",
            &p("bad.json"),
            "--out",
            &p("x.mp4"),
        ]),
        &["bad.json", "camera_path[1].fov"],
    );
    fails_naming(
        &stegongp(&[
            "video",
            "--model",
            &m,
            "--path",
            &p("missing.json"),
            "--out",
            &p("x.mp4"),
        ]),
        &["missing.json"],
    );
    fails_naming(&stegongp(&["video", "--model", &m]), &["--out"]);
    fails_naming(
        &stegongp(&["video", "--model", &m, "--out", &p("x.avi")]),
        &[".mp4"],
    );
    fails_naming(
        &stegongp(&["video", "--model", &m, "--out", &p("no/dir/x.mp4")]),
        &["does not exist"],
    );
    fails_naming(
        &stegongp(&[
            "video",
            "--model",
            &m,
            "--frames",
            "0",
            "--out",
            &p("x.mp4"),
        ]),
        &["--frames"],
    );
    // Nothing half-written was left behind.
    let left: Vec<_> = std::fs::read_dir(d.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(left.len(), 1, "{left:?}");
}

// ---------------------------------------------------------------------------------------------
// The viewer

struct Server {
    child: Child,
    url: String,
    port: u16,
    token: String,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start_viewer(args: &[&str]) -> Server {
    let mut child = Command::new(bin())
        .arg("view")
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let url = line
        .trim()
        .strip_prefix("open ")
        .unwrap_or_else(|| panic!("no URL in {line:?}"))
        .to_string();
    let port: u16 = url
        .split(':')
        .nth(2)
        .unwrap()
        .split('/')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    let token = url.split("token=").nth(1).unwrap().to_string();
    Server {
        child,
        url,
        port,
        token,
    }
}

/// A raw HTTP/1.1 GET with the given Host header: (status, body).
fn http_get(port: u16, path: &str, host: &str) -> (u16, String) {
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut resp = String::new();
    s.read_to_string(&mut resp).unwrap();
    let status = resp.split(' ').nth(1).unwrap().parse().unwrap();
    let body = resp.split("\r\n\r\n").nth(1).unwrap_or("").to_string();
    (status, body)
}

#[test]
fn viewer_refuses_requests_without_its_token_or_from_another_host() {
    let f = fixture();
    let d = tempfile::tempdir().unwrap();
    let rec = d.path().join("rec.json");
    let s = start_viewer(&[
        &f.p("m.ingp"),
        "--port",
        "0",
        "--record",
        rec.to_str().unwrap(),
    ]);
    let host = format!("127.0.0.1:{}", s.port);
    for path in [
        "/",
        "/info",
        "/frame?c2w=1,0,0,0.5,0,1,0,0.5,0,0,1,-1&fov=50&w=8&h=8",
    ] {
        assert_eq!(
            http_get(s.port, path, &host).0,
            403,
            "{path} without a token"
        );
        let wrong = format!(
            "{path}{}token=00{}",
            if path.contains('?') { "&" } else { "?" },
            &s.token[2..]
        );
        assert_eq!(
            http_get(s.port, &wrong, &host).0,
            403,
            "{path} with a wrong token"
        );
    }
    let info = format!("/info?token={}", s.token);
    // DNS rebinding: a page of evil.example whose name now points at 127.0.0.1.
    assert_eq!(
        http_get(s.port, &info, &format!("evil.example:{}", s.port)).0,
        403
    );
    let (status, body) = http_get(s.port, &info, &format!("localhost:{}", s.port));
    assert_eq!(status, 200, "{body}");
    assert!(body.contains("\"scene\":\"cover\""), "{body}");
    // Hostile frame requests get a 400, not a crash or a huge allocation.
    for q in [
        "c2w=1,2,3&fov=50&w=8&h=8",
        "c2w=1,0,0,0,0,1,0,0,0,0,1,0&fov=500&w=8&h=8",
        "c2w=1,0,0,0,0,1,0,0,0,0,1,0&fov=50&w=100000&h=100000",
        // Larger than the viewer's full frame (400×400 from the fixture's small cameras).
        "c2w=1,0,0,0,0,1,0,0,0,0,1,0&fov=50&w=1000&h=1000",
        "c2w=NaN,0,0,0,0,1,0,0,0,0,1,0&fov=50&w=8&h=8",
    ] {
        let (status, body) = http_get(s.port, &format!("/frame?{q}&token={}", s.token), &host);
        assert_eq!(status, 400, "{q}: {body}");
    }
    assert_eq!(http_get(s.port, &info, &host).0, 200, "the server survived");
    assert!(!rec.exists(), "nothing recorded, nothing written");
}

#[test]
fn viewer_in_a_real_browser() {
    let Some(chromium) = find_chromium() else {
        assert!(
            std::env::var_os("CI").is_none(),
            "CI must install Chromium (Debian's chromium package) for the viewer's browser test"
        );
        eprintln!("skipping the viewer's browser test: no Chromium (install Debian's chromium)");
        return;
    };
    let f = fixture();
    let d = tempfile::tempdir().unwrap();
    let rec = d.path().join("rec.json");
    let rec_s = rec.to_str().unwrap().to_string();
    let shots = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("viewer-screenshots");
    std::fs::create_dir_all(&shots).unwrap();
    let s = start_viewer(&[
        &f.p("m.ingp"),
        "--data",
        &f.p("cover"),
        "--port",
        "0",
        "--record",
        &rec_s,
        "--width",
        "96",
        "--height",
        "72",
        // An aim no frame meets: interactive frames shrink to the floor while dragging.
        "--frame-seconds",
        "0.0001",
    ]);
    let mut b = Browser::launch(&chromium, 900, 700);
    b.navigate(&s.url);
    b.wait_for(
        "window.viewer && viewer.fullFrames >= 1",
        Duration::from_secs(120),
    );
    b.screenshot(&shots.join("1-cover.png"));

    // The first full frame is the CLI's render of the same camera, recorded by the page.
    let canvas = |b: &mut Browser| -> Rgb8 {
        let url = b.eval("viewer.canvasPNG()");
        let bytes = decode_base64(url.as_str().unwrap().split(',').nth(1).unwrap());
        let p = d.path().join("canvas.png");
        std::fs::write(&p, bytes).unwrap();
        load_png(&p)
    };
    let record = |b: &mut Browser, n: usize| {
        b.eval("document.getElementById('record').click()");
        b.wait_for(
            &format!("document.getElementById('recmsg').textContent.startsWith('{n} camera')"),
            Duration::from_secs(30),
        );
    };
    let cli_frame = |key: Option<&str>, i: usize| -> Rgb8 {
        let out = d
            .path()
            .join(format!("cli-{}", key.map_or("cover", |_| "key")));
        let (m, data) = (f.p("m.ingp"), f.p("cover"));
        let mut a = vec!["video", "--model", &m, "--data", &data, "--path", &rec_s];
        let fd = out.to_str().unwrap().to_string();
        a.extend(["--frames-dir", &fd]);
        if let Some(k) = key {
            a.extend(["--key", k]);
        }
        ok(&stegongp(&a));
        load_png(&out.join(format!("frame_{i:05}.png")))
    };
    let first = canvas(&mut b);
    assert_eq!((first.width, first.height), (96, 72));
    record(&mut b, 1);
    let cli = cli_frame(None, 0);
    let p = first.psnr(&cli);
    assert!(
        p >= 30.0,
        "the page's first full frame is {p:.1} dB from the CLI's render"
    );

    // A drag orbits: interactive frames while moving, then a full frame of a new view.
    let (fast0, full0) = (
        b.eval("viewer.fastFrames").as_u64().unwrap(),
        b.eval("viewer.fullFrames").as_u64().unwrap(),
    );
    let rect = b.eval("(() => { const r = document.getElementById('view').getBoundingClientRect(); return [r.left, r.top, r.width, r.height]; })()");
    let r: Vec<f64> = rect
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect();
    let (cx, cy) = (r[0] + r[2] / 2.0, r[1] + r[3] / 2.0);
    b.drag((cx, cy), (cx + 120.0, cy + 20.0), 12);
    b.wait_for(
        &format!("viewer.fullFrames > {full0} && !viewer.inflight"),
        Duration::from_secs(60),
    );
    assert!(
        b.eval("viewer.fastFrames").as_u64().unwrap() > fast0,
        "no interactive frame while dragging"
    );
    let moved = canvas(&mut b);
    assert!(
        moved.psnr(&first) < 30.0,
        "the drag did not change the view"
    );
    // Dynamic resolution: the interactive frames shrank toward the aim, no lower than 1/16
    // of the full size; the rule grows them at most twofold a frame, up to the largest.
    let scale = b.eval("viewer.fastScale").as_f64().unwrap();
    assert!(
        (1.0 / 16.0..0.25).contains(&scale),
        "interactive scale {scale} after frames slower than the aim"
    );
    let adapt = |b: &mut Browser, from: f64, times_aim: f64| -> f64 {
        b.eval(&format!(
            "(() => {{ viewer.fastScale = {from}; viewer.adapt(viewer.info.frame_seconds * {times_aim}); return viewer.fastScale; }})()"
        ))
        .as_f64()
        .unwrap()
    };
    assert!((adapt(&mut b, 0.1, 0.25) - 0.2).abs() < 1e-9);
    assert!((adapt(&mut b, 0.1, 0.01) - 0.2).abs() < 1e-9);
    assert!((adapt(&mut b, 0.2, 0.01) - 0.25).abs() < 1e-9);
    assert!((adapt(&mut b, 0.07, 100.0) - 1.0 / 16.0).abs() < 1e-9);
    assert!((adapt(&mut b, 0.1, 1.0) - 0.1).abs() < 1e-9);
    b.screenshot(&shots.join("2-dragged.png"));
    record(&mut b, 2);

    // The key file, picked in the page, shows the hidden scene as the CLI renders it.
    b.set_file("#keyfile", &f.dir.join("k.json"));
    let full1 = b.eval("viewer.fullFrames").as_u64().unwrap();
    b.eval("document.getElementById('unlock').click()");
    b.wait_for(
        &format!("viewer.scene === 'key' && viewer.fullFrames > {full1} && !viewer.inflight"),
        Duration::from_secs(120),
    );
    let keyed = canvas(&mut b);
    b.screenshot(&shots.join("3-key.png"));
    let cli_key = cli_frame(Some(&f.p("k.json")), 1);
    let p = keyed.psnr(&cli_key);
    assert!(
        p >= 25.0,
        "the page's hidden scene is {p:.1} dB from the CLI's keyed render"
    );
    let key_file_in_page = b.eval("document.getElementById('keyfile').files.length");
    assert_eq!(
        key_file_in_page, 0,
        "the page keeps the key file after unlocking"
    );

    // A wrong key, as a passphrase and salt, shows what it shows: not the hidden scene.
    let full2 = b.eval("viewer.fullFrames").as_u64().unwrap();
    b.eval("document.getElementById('pass').value = 'not the passphrase'; document.getElementById('salt').value = 'somesalt'; document.getElementById('unlock').click()");
    b.wait_for(&format!("document.getElementById('keymsg').textContent.startsWith('hidden scene open') && viewer.fullFrames > {full2} && !viewer.inflight"), Duration::from_secs(120));
    let wrong = canvas(&mut b);
    b.screenshot(&shots.join("4-wrong-key.png"));
    let p_wrong = wrong.psnr(&cli_key);
    assert!(
        p_wrong < 25.0 && p_wrong < p - 10.0,
        "a wrong key shows the hidden scene ({p_wrong:.1} dB)"
    );

    // Forgetting the key brings the cover back.
    let full3 = b.eval("viewer.fullFrames").as_u64().unwrap();
    b.eval("document.querySelector('#forget').click()");
    b.wait_for(
        &format!("viewer.scene === 'cover' && viewer.fullFrames > {full3} && !viewer.inflight"),
        Duration::from_secs(60),
    );
    let cover_again = canvas(&mut b);
    let cli_cover = cli_frame(None, 1);
    assert!(
        cover_again.psnr(&cli_cover) >= 30.0,
        "forgetting the key does not bring the cover back"
    );

    // The page loaded nothing from elsewhere and logged no error.
    assert!(
        b.console_errors.is_empty(),
        "console: {:?}",
        b.console_errors
    );
    let errors = b.eval("viewer.errors");
    assert_eq!(errors, serde_json::json!([]), "page errors");
    eprintln!("viewer screenshots in {}", shots.display());
}

#[test]
fn a_browser_plays_the_video() {
    let Some(chromium) = find_chromium() else {
        assert!(std::env::var_os("CI").is_none(), "CI must install Chromium");
        eprintln!("skipping: no Chromium (install Debian's chromium)");
        return;
    };
    let f = fixture();
    let d = tempfile::tempdir().unwrap();
    let mp4 = d.path().join("orbit.mp4");
    ok(&stegongp(&[
        "video",
        "--model",
        &f.p("m.ingp"),
        "--frames",
        "12",
        "--fps",
        "24",
        "--width",
        "64",
        "--height",
        "48",
        "--out",
        mp4.to_str().unwrap(),
    ]));
    let page = d.path().join("play.html");
    std::fs::write(
        &page,
        r#"<!doctype html><video id="v" src="orbit.mp4" muted></video><script>
        const v = document.getElementById('v');
        window.played = new Promise((ok) => {
          v.addEventListener('loadeddata', () => ok([v.videoWidth, v.videoHeight, v.duration]));
          v.addEventListener('error', () => ok('error ' + (v.error && v.error.code)));
        });
        </script>"#,
    )
    .unwrap();
    let mut b = Browser::launch(&chromium, 400, 300);
    b.navigate(&format!("file://{}", page.display()));
    b.wait_for(
        "typeof window.played !== 'undefined'",
        Duration::from_secs(30),
    );
    let r = b.eval("window.played");
    assert_eq!(
        r,
        serde_json::json!([64, 48, 0.5]),
        "Chromium's player: {r}"
    );
}

#[test]
fn demo_writes_its_side_by_side_video_and_large_figure() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("demo");
    let o = out.to_str().unwrap();
    let log = ok(&stegongp(&[
        "demo",
        "--out",
        o,
        "--res",
        "24",
        "--steps",
        "5",
        "--batch",
        "4096",
        "--video-frames",
        "3",
        "--figure-size",
        "40",
        "--video-size",
        "20",
    ]));
    let large = load_png(&out.join("demo_large.png"));
    // Three 40-px panels, two 4-px gaps.
    assert_eq!((large.width, large.height), (128, 40), "{log}");
    let v = decode_mp4(&out.join("demo.mp4")).unwrap();
    assert_eq!((v.width, v.height, v.frames.len()), (68, 20, 3));
}

#[test]
fn view_refuses_bad_frame_options_before_listening() {
    let f = fixture();
    let m = f.p("m.ingp");
    for (flag, value) in [
        ("--interactive-scale", "0"),
        ("--interactive-scale", "1.5"),
        ("--frame-seconds", "-1"),
        ("--frame-seconds", "NaN"),
        ("--frame-seconds", "inf"),
    ] {
        let out = stegongp(&["view", &m, &format!("{flag}={value}"), "--port", "0"]);
        fails_naming(&out, &[flag]);
        assert!(
            !String::from_utf8_lossy(&out.stdout).contains("open "),
            "{flag} {value}: the viewer started"
        );
    }
}
