//! H.264 (4:2:0, BT.601 limited range, signalled in the stream) in an MP4 that ordinary
//! players and browsers open; and reading one back, frame by frame, with the same codec's
//! decoder. The file appears under its name only when complete: frames go to a temporary
//! file beside it, synced and renamed at the end.

use crate::frame::{Rgb8, bt601};
use mp4::{
    AvcConfig, MediaConfig, Mp4Config, Mp4Reader, Mp4Sample, Mp4Writer, TrackConfig, TrackType,
};
use ngp::error::{Error, Result};
use openh264::OpenH264API;
use openh264::decoder::Decoder;
use openh264::encoder::{
    BitRate, Complexity, Encoder, EncoderConfig, FrameRate, FrameType, IntraFramePeriod, Level,
    QpRange, RateControlMode, VuiConfig,
};
use openh264::formats::{YUVBuffer, YUVSource};
use std::fs::File;
use std::io::{BufReader, BufWriter};
use std::path::{Path, PathBuf};

/// Largest frame side the encoder takes (H.264 level 5.2 allows 4096×2304 at most).
pub const MAX_VIDEO_SIDE: u32 = 4096;

/// How a video was written.
#[derive(Clone, Debug, serde::Serialize)]
pub struct VideoSummary {
    pub path: PathBuf,
    pub width: u32,
    pub height: u32,
    pub frames: u32,
    pub fps: u32,
    pub bytes: u64,
    /// Seconds spent converting and encoding (not rendering).
    pub encode_seconds: f64,
}

/// An MP4 being written.
pub struct Mp4Video {
    dest: PathBuf,
    mp4: Option<Mp4Writer<BufWriter<File>>>,
    encoder: Encoder,
    width: u32,
    height: u32,
    fps: u32,
    frames: u32,
    track_added: bool,
    encode_seconds: f64,
    sample: Vec<u8>,
    /// Removes the temporary file when the video is dropped unfinished or finishing fails;
    /// last, so that it is dropped after the writer has closed the file.
    pending: ngp::util::PendingFile,
}

fn nal_type(nal: &[u8]) -> Option<u8> {
    // Encoder NAL units start with a 3- or 4-byte start code.
    let body = nal
        .strip_prefix(&[0, 0, 0, 1])
        .or_else(|| nal.strip_prefix(&[0, 0, 1]))?;
    body.first().map(|b| b & 0x1f)
}

fn strip_start_code(nal: &[u8]) -> &[u8] {
    nal.strip_prefix(&[0, 0, 0, 1])
        .or_else(|| nal.strip_prefix(&[0, 0, 1]))
        .unwrap_or(nal)
}

impl Mp4Video {
    /// Starts `path` (its folder must exist) for `width`×`height` frames (even sides) at
    /// `fps`.
    pub fn create(path: &Path, width: u32, height: u32, fps: u32) -> Result<Self> {
        if !width.is_multiple_of(2) || !height.is_multiple_of(2) || width == 0 || height == 0 {
            return Err(Error::format(
                path,
                format!("{width}x{height}: H.264 4:2:0 needs even, non-zero sides"),
            ));
        }
        if width > MAX_VIDEO_SIDE || height > MAX_VIDEO_SIDE {
            return Err(Error::format(
                path,
                format!("{width}x{height}: larger than {MAX_VIDEO_SIDE} pixels a side"),
            ));
        }
        if !(1..=240).contains(&fps) {
            return Err(Error::format(
                path,
                format!("{fps} frames per second: not in 1..=240"),
            ));
        }
        let (pending, file) = ngp::util::PendingFile::create(path)?;
        let config = Mp4Config {
            major_brand: "isom".parse().expect("a four-character code"),
            minor_version: 512,
            compatible_brands: ["isom", "iso2", "avc1", "mp41"]
                .iter()
                .map(|b| b.parse().expect("a four-character code"))
                .collect(),
            timescale: 1000,
        };
        let mut video = Mp4Video {
            dest: path.to_path_buf(),
            pending,
            mp4: None,
            encoder: Encoder::with_api_config(
                OpenH264API::from_source(),
                EncoderConfig::new()
                    // Quantiser 12–18 held by buffer-based control: within ~0.4 dB of what
                    // 4:2:0 itself keeps (lego ×4 at 200 and 400 px). The bit-rate modes
                    // measure the same and warn on the terminal that a rate cannot be held
                    // without skipping frames, which a video must not do.
                    .rate_control_mode(RateControlMode::Bufferbased)
                    .bitrate(BitRate::from_bps(
                        (width * height * fps)
                            .saturating_mul(12)
                            .clamp(2_000_000, 240_000_000),
                    ))
                    .max_frame_rate(FrameRate::from_hz(fps as f32))
                    .qp(QpRange::new(12, 18))
                    // Without a level the encoder picks the smallest the frame size allows,
                    // and clips the bit rate to that level's (64 kbit/s for a small frame).
                    .level(Level::Level_5_1)
                    .skip_frames(false)
                    .complexity(Complexity::High)
                    // Adaptive quantisation and background detection spend fewer bits where
                    // the eye is said to look less; a render is compared pixel by pixel.
                    .adaptive_quantization(false)
                    .background_detection(false)
                    .intra_frame_period(IntraFramePeriod::from_num_frames(2 * fps))
                    .vui(VuiConfig::bt601())
                    .debug(false),
            )
            .map_err(|e| Error::format(path, format!("H.264 encoder: {e}")))?,
            width,
            height,
            fps,
            frames: 0,
            track_added: false,
            encode_seconds: 0.0,
            sample: Vec::new(),
        };
        let mp4 = Mp4Writer::write_start(BufWriter::new(file), &config).map_err(|e| video.fail(e));
        video.mp4 = Some(mp4?);
        Ok(video)
    }

    fn fail(&self, e: impl std::fmt::Display) -> Error {
        Error::format(&self.dest, format!("writing the video: {e}"))
    }

    /// Appends one frame (its size must be the video's).
    pub fn push(&mut self, frame: &Rgb8) -> Result<()> {
        if (frame.width, frame.height) != (self.width, self.height) {
            return Err(self.fail(format!(
                "a {}x{} frame in a {}x{} video",
                frame.width, frame.height, self.width, self.height
            )));
        }
        let t0 = std::time::Instant::now();
        let yuv = rgb_to_yuv420(frame);
        let stream = self
            .encoder
            .encode(&yuv)
            .map_err(|e| Error::format(&self.dest, format!("H.264 encoder: {e}")))?;
        let is_sync = matches!(stream.frame_type(), FrameType::IDR | FrameType::I);
        let (mut sps, mut pps) = (None, None);
        self.sample.clear();
        for l in 0..stream.num_layers() {
            let Some(layer) = stream.layer(l) else {
                continue;
            };
            for n in 0..layer.nal_count() {
                let Some(nal) = layer.nal_unit(n) else {
                    continue;
                };
                match nal_type(nal) {
                    Some(7) => sps = Some(strip_start_code(nal).to_vec()),
                    Some(8) => pps = Some(strip_start_code(nal).to_vec()),
                    _ => {
                        // MP4 samples hold length-prefixed NAL units, not start codes.
                        let body = strip_start_code(nal);
                        self.sample
                            .extend_from_slice(&(body.len() as u32).to_be_bytes());
                        self.sample.extend_from_slice(body);
                    }
                }
            }
        }
        let mp4 = self.mp4.as_mut().expect("open until finish");
        if !self.track_added {
            let (Some(sps), Some(pps)) = (sps, pps) else {
                return Err(Error::format(
                    &self.dest,
                    "the encoder's first frame carries no SPS/PPS",
                ));
            };
            let track = TrackConfig {
                track_type: TrackType::Video,
                timescale: 1000 * self.fps,
                language: "und".into(),
                media_conf: MediaConfig::AvcConfig(AvcConfig {
                    width: self.width as u16,
                    height: self.height as u16,
                    seq_param_set: sps,
                    pic_param_set: pps,
                }),
            };
            mp4.add_track(&track)
                .map_err(|e| Error::format(&self.dest, format!("writing the video: {e}")))?;
            self.track_added = true;
        }
        let sample = Mp4Sample {
            start_time: self.frames as u64 * 1000,
            duration: 1000,
            rendering_offset: 0,
            is_sync,
            bytes: bytes::Bytes::copy_from_slice(&self.sample),
        };
        mp4.write_sample(1, &sample)
            .map_err(|e| Error::format(&self.dest, format!("writing the video: {e}")))?;
        self.frames += 1;
        self.encode_seconds += t0.elapsed().as_secs_f64();
        Ok(())
    }

    /// Closes the MP4 and puts it under its name.
    pub fn finish(mut self) -> Result<VideoSummary> {
        if self.frames == 0 {
            return Err(self.fail("no frames"));
        }
        let mut mp4 = self.mp4.take().expect("open until finish");
        mp4.write_end().map_err(|e| self.fail(e))?;
        let file = mp4
            .into_writer()
            .into_inner()
            .map_err(|e| Error::io(&self.dest, e.into_error()))?;
        let bytes = file.metadata().map_err(|e| Error::io(&self.dest, e))?.len();
        self.pending.commit(file)?;
        Ok(VideoSummary {
            path: self.dest,
            width: self.width,
            height: self.height,
            frames: self.frames,
            fps: self.fps,
            bytes,
            encode_seconds: self.encode_seconds,
        })
    }
}

/// I420 planes of an even-sided frame: luma per pixel, chroma of each 2×2 block's mean.
fn rgb_to_yuv420(f: &Rgb8) -> YUVBuffer {
    let (w, h) = (f.width as usize, f.height as usize);
    let mut yuv = vec![0u8; w * h + 2 * (w / 2) * (h / 2)];
    let (ys, uv) = yuv.split_at_mut(w * h);
    let (us, vs) = uv.split_at_mut((w / 2) * (h / 2));
    for by in 0..h / 2 {
        for bx in 0..w / 2 {
            let mut mean = [0.0f32; 3];
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let (x, y) = (2 * bx + dx, 2 * by + dy);
                let i = 3 * (y * w + x);
                let p = [f.data[i] as f32, f.data[i + 1] as f32, f.data[i + 2] as f32];
                ys[y * w + x] = bt601::code(bt601::to_ycbcr(p)[0]);
                for c in 0..3 {
                    mean[c] += 0.25 * p[c];
                }
            }
            let [_, cb, cr] = bt601::to_ycbcr(mean);
            us[by * (w / 2) + bx] = bt601::code(cb);
            vs[by * (w / 2) + bx] = bt601::code(cr);
        }
    }
    YUVBuffer::from_vec(yuv, w, h)
}

/// RGB of decoded I420 planes (chroma repeated over its 2×2 block), rounded.
fn yuv420_to_rgb(yuv: &impl YUVSource) -> Rgb8 {
    let (w, h) = yuv.dimensions();
    let (sy, su, sv) = yuv.strides();
    let (yp, up, vp) = (yuv.y(), yuv.u(), yuv.v());
    let mut data = vec![0u8; 3 * w * h];
    for y in 0..h {
        for x in 0..w {
            let (c, r) = ((y / 2) * su + x / 2, (y / 2) * sv + x / 2);
            let rgb = bt601::to_rgb([yp[y * sy + x] as f32, up[c] as f32, vp[r] as f32]);
            let i = 3 * (y * w + x);
            for (o, v) in data[i..i + 3].iter_mut().zip(rgb) {
                *o = bt601::code(v);
            }
        }
    }
    Rgb8 {
        width: w as u32,
        height: h as u32,
        data,
    }
}

/// What an MP4 holds, decoded.
pub struct DecodedVideo {
    pub width: u32,
    pub height: u32,
    /// Frames per second from the track's sample durations.
    pub fps: f64,
    pub frames: Vec<Rgb8>,
}

/// Decodes the first H.264 track of `path` into RGB frames.
pub fn decode_mp4(path: &Path) -> Result<DecodedVideo> {
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    let size = file.metadata().map_err(|e| Error::io(path, e))?.len();
    let bad = |e: &dyn std::fmt::Display| Error::format(path, format!("reading the video: {e}"));
    let mut mp4 = Mp4Reader::read_header(BufReader::new(file), size).map_err(|e| bad(&e))?;
    let (id, track) = mp4
        .tracks()
        .iter()
        .find(|(_, t)| {
            t.media_type()
                .map(|m| m == mp4::MediaType::H264)
                .unwrap_or(false)
        })
        .map(|(id, t)| (*id, t))
        .ok_or_else(|| Error::format(path, "no H.264 track"))?;
    let (width, height) = (track.width() as u32, track.height() as u32);
    let fps = track.frame_rate();
    let mut annexb = Vec::new();
    for ps in [
        track.sequence_parameter_set(),
        track.picture_parameter_set(),
    ] {
        annexb.extend_from_slice(&[0, 0, 0, 1]);
        annexb.extend_from_slice(ps.map_err(|e| bad(&e))?);
    }
    let n = mp4.sample_count(id).map_err(|e| bad(&e))?;
    let mut decoder = Decoder::new().map_err(|e| bad(&e))?;
    let mut frames = Vec::with_capacity(n as usize);
    let take = |yuv: &openh264::decoder::DecodedYUV<'_>, frames: &mut Vec<Rgb8>| {
        frames.push(yuv420_to_rgb(yuv));
    };
    for s in 1..=n {
        let Some(sample) = mp4.read_sample(id, s).map_err(|e| bad(&e))? else {
            continue;
        };
        let mut packet = std::mem::take(&mut annexb);
        let mut rest: &[u8] = &sample.bytes;
        while rest.len() >= 4 {
            let len = u32::from_be_bytes([rest[0], rest[1], rest[2], rest[3]]) as usize;
            let body = rest.get(4..4 + len).ok_or_else(|| {
                Error::format(path, format!("sample {s}: a NAL unit runs past its sample"))
            })?;
            packet.extend_from_slice(&[0, 0, 0, 1]);
            packet.extend_from_slice(body);
            rest = &rest[4 + len..];
        }
        if let Some(yuv) = decoder.decode(&packet).map_err(|e| bad(&e))? {
            take(&yuv, &mut frames);
        }
    }
    for yuv in decoder.flush_remaining().map_err(|e| bad(&e))? {
        take(&yuv, &mut frames);
    }
    Ok(DecodedVideo {
        width,
        height,
        fps,
        frames,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A moving gradient with a square: enough texture that a codec has work to do.
    fn test_frame(w: u32, h: u32, t: u32) -> Rgb8 {
        let mut f = Rgb8::new(w, h, [0, 0, 0]);
        for y in 0..h {
            for x in 0..w {
                let i = 3 * (y * w + x) as usize;
                f.data[i] = ((x * 255) / w) as u8;
                f.data[i + 1] = ((y * 255) / h) as u8;
                // A soft blob moving right: renders have edges, but 4:2:0 halves the chroma
                // of any edge, so a hard-edged test pattern would measure the format, not us.
                let (dx, dy) = (
                    (x + 2 * t) as f32 - w as f32 / 2.0,
                    y as f32 - h as f32 / 2.0,
                );
                f.data[i + 2] = (40.0 + 210.0 * (-(dx * dx + dy * dy) / 60.0).exp()) as u8;
            }
        }
        f
    }

    #[test]
    fn mp4_decodes_to_the_frames_written() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.mp4");
        let (w, h) = (96, 64);
        let mut v = Mp4Video::create(&path, w, h, 24).unwrap();
        let frames: Vec<Rgb8> = (0..12).map(|t| test_frame(w, h, t)).collect();
        for f in &frames {
            v.push(f).unwrap();
        }
        let s = v.finish().unwrap();
        assert_eq!((s.frames, s.width, s.height), (12, w, h));
        // Only the finished file is left.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
        let d = decode_mp4(&path).unwrap();
        assert_eq!((d.width, d.height), (w, h));
        assert_eq!(d.frames.len(), 12);
        assert!((d.fps - 24.0).abs() < 0.01, "{}", d.fps);
        for (a, b) in d.frames.iter().zip(&frames) {
            let p = a.psnr(b);
            assert!(p > 35.0, "decoded frame {p:.1} dB from the written one");
        }
    }

    #[test]
    fn bad_sizes_and_dropped_videos_leave_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.mp4");
        assert!(
            Mp4Video::create(&path, 31, 20, 24)
                .err()
                .unwrap()
                .to_string()
                .contains("even")
        );
        assert!(Mp4Video::create(&path, 32, 20, 0).is_err());
        let mut v = Mp4Video::create(&path, 32, 20, 24).unwrap();
        assert!(v.push(&Rgb8::new(30, 20, [0; 3])).is_err());
        v.push(&Rgb8::new(32, 20, [9; 3])).unwrap();
        drop(v);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        let missing = dir.path().join("no/such/dir/v.mp4");
        assert!(Mp4Video::create(&missing, 32, 20, 24).is_err());
        // A video that fails to finish leaves an older file under the name as it was.
        std::fs::write(&path, b"old video").unwrap();
        let v = Mp4Video::create(&path, 32, 20, 24).unwrap();
        assert!(v.finish().is_err());
        assert_eq!(std::fs::read(&path).unwrap(), b"old video");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn a_file_that_is_not_a_video_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.mp4");
        std::fs::write(&path, b"\x00\x00\x00\x18ftypisom garbage garbage").unwrap();
        assert!(decode_mp4(&path).is_err());
    }
}
