//! A video's frames: probed with ffprobe, decoded once by ffmpeg into a pipe of PPM images
//! (each carries its size, so ffmpeg's rotation of a phone's portrait clip needs no guess),
//! and the sharpest frame of each of `N` equal stretches of the clip kept, as colmap2nerf
//! scores frames (variance of the Laplacian) but choosing instead of merely recording.

use crate::Progress;
use crate::pixels::{sharpness, write_png};
use crate::tools::{Tool, first_line};
use anyhow::{Context, Result, anyhow, bail};
use ngp::data::image::MAX_IMAGE_PIXELS;
use std::io::{BufRead, BufReader, Read};
use std::path::Path;
use std::process::Stdio;

/// What ffprobe says of a video's first video stream.
#[derive(Clone, Debug)]
pub struct Probe {
    pub codec: String,
    pub width: u32,
    pub height: u32,
    /// Packets of the stream (one a frame), counted by reading the file without decoding.
    pub frames: u64,
    pub seconds: Option<f64>,
}

fn num(v: &serde_json::Value) -> Option<f64> {
    v.as_f64()
        .or_else(|| v.as_str().and_then(|s| s.parse().ok()))
}

/// Probes `input`, refusing what is not a video ffmpeg decodes.
pub fn probe(ffprobe: &Tool, input: &Path) -> Result<Probe> {
    let out = ffprobe.output([
        "-v".as_ref(),
        "error".as_ref(),
        "-select_streams".as_ref(),
        "v:0".as_ref(),
        "-count_packets".as_ref(),
        "-show_entries".as_ref(),
        "stream=codec_name,width,height,nb_read_packets,duration:format=format_name,duration"
            .as_ref(),
        "-of".as_ref(),
        "json".as_ref(),
        input.as_os_str(),
    ])?;
    let not_video = |why: String| {
        anyhow!(
            "{}: not a video ffmpeg can read ({why}); give a video file (MP4, MOV, …) or a \
             folder of photos",
            input.display()
        )
    };
    if !out.status.success() {
        return Err(not_video(format!("ffprobe: {}", first_line(&out.stderr))));
    }
    let v: serde_json::Value = serde_json::from_slice(&out.stdout)
        .map_err(|e| not_video(format!("ffprobe's answer: {e}")))?;
    let format = v["format"]["format_name"].as_str().unwrap_or("");
    let s = v["streams"]
        .get(0)
        .ok_or_else(|| not_video(format!("no video stream in this {format} file")))?;
    let codec = s["codec_name"].as_str().unwrap_or("?").to_string();
    if format == "image2" || format.ends_with("_pipe") {
        bail!(
            "{}: a single {codec} image, not a video: give the folder that holds the photos",
            input.display()
        );
    }
    let dim = |k: &str| num(&s[k]).filter(|d| *d >= 1.0).map(|d| d as u32);
    let (Some(width), Some(height)) = (dim("width"), dim("height")) else {
        return Err(not_video(format!("its {codec} stream has no frame size")));
    };
    let frames = num(&s["nb_read_packets"]).unwrap_or(0.0) as u64;
    if frames < 3 {
        return Err(not_video(format!(
            "its {codec} stream holds {frames} frame(s); a capture needs many"
        )));
    }
    let seconds = num(&s["duration"]).or_else(|| num(&v["format"]["duration"]));
    Ok(Probe {
        codec,
        width,
        height,
        frames,
        seconds,
    })
}

/// The frames written, and what was decoded.
#[derive(Debug)]
pub struct Extracted {
    /// Image names in `images/`, in clip order: `frame_NNNNNN.png`, the source frame's index.
    pub names: Vec<String>,
    pub decoded: u64,
    pub width: u32,
    pub height: u32,
}

/// Reads one PPM header (`P6 W H 255`) from `r`; None at a clean end of the stream.
fn ppm_header(r: &mut impl BufRead) -> Result<Option<(u32, u32)>> {
    if r.fill_buf()?.is_empty() {
        return Ok(None);
    }
    let mut fields = Vec::with_capacity(4);
    let mut cur = Vec::new();
    while fields.len() < 4 {
        let mut b = [0u8];
        r.read_exact(&mut b)
            .context("ffmpeg's frame stream ended inside a header")?;
        if b[0] == b'#' {
            let mut skip = Vec::new();
            r.read_until(b'\n', &mut skip)?;
        } else if b[0].is_ascii_whitespace() {
            if !cur.is_empty() {
                fields.push(String::from_utf8_lossy(&std::mem::take(&mut cur)).into_owned());
            }
        } else if cur.len() < 16 {
            cur.push(b[0]);
        } else {
            bail!("ffmpeg's frame stream: a PPM header field too long");
        }
    }
    let n = |s: &str| s.parse::<u32>().ok();
    match (
        fields[0].as_str(),
        n(&fields[1]),
        n(&fields[2]),
        n(&fields[3]),
    ) {
        ("P6", Some(w), Some(h), Some(255))
            if w > 0 && h > 0 && (w as u64 * h as u64) <= MAX_IMAGE_PIXELS =>
        {
            Ok(Some((w, h)))
        }
        _ => bail!("ffmpeg's frame stream: unexpected PPM header {fields:?}"),
    }
}

/// The best frame of the stretch being read.
struct Best {
    window: u64,
    index: u64,
    score: f64,
    rgb: Vec<u8>,
    size: (u32, u32),
}

/// ffmpeg's arguments: the first video stream, the long side capped (never enlarged),
/// every decoded frame passed through once, as 8-bit RGB PPMs.
fn ffmpeg_args(
    input: &Path,
    max_side: u32,
    ffmpeg_version: Option<(u32, u32)>,
) -> Vec<std::ffi::OsString> {
    let mut a: Vec<std::ffi::OsString> = ["-nostdin", "-hide_banner", "-loglevel", "error", "-i"]
        .iter()
        .map(Into::into)
        .collect();
    a.push(input.as_os_str().into());
    for s in ["-map", "0:v:0", "-an", "-sn", "-dn"] {
        a.push(s.into());
    }
    if max_side > 0 {
        a.push("-vf".into());
        a.push(
            format!(
                "scale=w='min({max_side},iw)':h='min({max_side},ih)':\
                 force_original_aspect_ratio=decrease:flags=area"
            )
            .into(),
        );
    }
    // -fps_mode replaced -vsync in ffmpeg 5.1; either keeps every frame once, undropped
    // and unduplicated.
    let sync = if ffmpeg_version.is_some_and(|v| v >= (5, 1)) {
        "-fps_mode"
    } else {
        "-vsync"
    };
    for s in [
        sync,
        "passthrough",
        "-pix_fmt",
        "rgb24",
        "-c:v",
        "ppm",
        "-f",
        "image2pipe",
    ] {
        a.push(s.into());
    }
    a.push("pipe:1".into());
    a
}

/// The frames asked for: about `frames` of them, the long side at most `max_side` (0: as
/// decoded).
pub struct Wanted {
    pub frames: usize,
    pub max_side: u32,
}

/// Decodes `input` once and writes the sharpest frame of each of `want.frames` equal
/// stretches (by frame count) into `images`.
pub fn extract(
    ffmpeg: &Tool,
    ffmpeg_version: Option<(u32, u32)>,
    input: &Path,
    probe: &Probe,
    want: &Wanted,
    images: &Path,
    pb: &dyn Progress,
) -> Result<Extracted> {
    let mut child = ffmpeg
        .command()
        .args(ffmpeg_args(input, want.max_side, ffmpeg_version))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| ffmpeg.spawn_error(e))?;
    let mut err = child.stderr.take().expect("piped stderr");
    let err_reader = std::thread::spawn(move || {
        let mut s = Vec::new();
        let _ = err.read_to_end(&mut s);
        s
    });
    let mut r = BufReader::with_capacity(1 << 20, child.stdout.take().expect("piped stdout"));
    let windows = (want.frames as u64).min(probe.frames).max(1);
    let mut out = Extracted {
        names: Vec::new(),
        decoded: 0,
        width: 0,
        height: 0,
    };
    let mut best: Option<Best> = None;
    let mut cur = Vec::new();
    let read = (|| -> Result<()> {
        while let Some((w, h)) = ppm_header(&mut r)? {
            cur.resize(3 * w as usize * h as usize, 0);
            r.read_exact(&mut cur)
                .context("ffmpeg's frame stream ended inside a frame")?;
            let i = out.decoded;
            out.decoded += 1;
            pb.set_position(out.decoded.min(probe.frames));
            let window = (i * windows / probe.frames).min(windows - 1);
            let score = sharpness(&cur, w as usize, h as usize);
            if let Some(b) = best.take_if(|b| b.window != window) {
                keep(&b, images, &mut out)?;
            }
            if best.as_ref().is_none_or(|b| score > b.score) {
                // This frame's pixels are kept; the buffer of the one it replaces takes the
                // next frame.
                let spare = best.take().map(|b| b.rgb).unwrap_or_default();
                best = Some(Best {
                    window,
                    index: i,
                    score,
                    rgb: std::mem::replace(&mut cur, spare),
                    size: (w, h),
                });
            }
        }
        if let Some(b) = best.take() {
            keep(&b, images, &mut out)?;
        }
        Ok(())
    })();
    if read.is_err() {
        let _ = child.kill();
    }
    let status = child.wait().context("waiting for ffmpeg")?;
    let stderr = err_reader.join().unwrap_or_default();
    if !status.success() {
        let text = String::from_utf8_lossy(&stderr);
        let tail: Vec<&str> = text.lines().rev().take(8).collect::<Vec<_>>();
        let tail: Vec<&str> = tail.into_iter().rev().collect();
        bail!(
            "ffmpeg could not decode {} ({status}):\n  {}",
            input.display(),
            tail.join("\n  ")
        );
    }
    read?;
    if out.names.len() < 3 {
        bail!(
            "{}: ffmpeg decoded {} frame(s) of the {} its {} stream holds; a capture needs many",
            input.display(),
            out.decoded,
            probe.frames,
            probe.codec
        );
    }
    Ok(out)
}

/// Writes a stretch's chosen frame.
fn keep(b: &Best, images: &Path, out: &mut Extracted) -> Result<()> {
    let name = format!("frame_{:06}.png", b.index);
    let (w, h) = b.size;
    if out.names.is_empty() {
        (out.width, out.height) = (w, h);
    } else if (w, h) != (out.width, out.height) {
        bail!(
            "the video's frame size changes ({}x{} then {w}x{h} at frame {}): not supported",
            out.width,
            out.height,
            b.index
        );
    }
    write_png(&images.join(&name), w, h, 3, &b.rgb)?;
    out.names.push(name);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ppm_headers_parse_and_bad_ones_are_refused() {
        let mut r = std::io::Cursor::new(b"P6\n4 2\n255\nxxxxxxxxxxxxxxxxxxxxxxxx".to_vec());
        assert_eq!(ppm_header(&mut r).unwrap(), Some((4, 2)));
        let mut rest = Vec::new();
        r.read_to_end(&mut rest).unwrap();
        assert_eq!(rest.len(), 24);
        let mut r = std::io::Cursor::new(b"P6 # c\n3 3 255 ".to_vec());
        assert_eq!(ppm_header(&mut r).unwrap(), Some((3, 3)));
        assert_eq!(
            ppm_header(&mut std::io::Cursor::new(Vec::new())).unwrap(),
            None
        );
        for bad in [
            &b"P5\n4 2\n255\n"[..],
            b"P6\n4 2\n65535\n",
            b"P6\n0 2\n255\n",
            b"P6\n99999 99999\n255\n",
            b"P6\n4",
        ] {
            assert!(ppm_header(&mut std::io::Cursor::new(bad.to_vec())).is_err());
        }
    }
}
