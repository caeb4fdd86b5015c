//! `encode`: frames written as an H.264 MP4 (OpenH264's encoder, built from source,
//! and the `mp4` crate's muxer), for `predict --video --draw` and `synth --video`.
//!
//! Frames must all have the size of the first; an odd width or height loses its last
//! column or row (H.264's 4:2:0 pictures have even sides). The file is written under a
//! temporary name and renamed into place by [`Mp4Encoder::finish`]: a run stopped
//! half-way leaves no partial video.

use arkit_core::{Error, Result};
use image::RgbImage;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

/// The time units of a second in the files written.
const TIMESCALE: u32 = 90_000;

/// An H.264 MP4 being written (see the module docs).
pub struct Mp4Encoder {
    path: PathBuf,
    tmp: PathBuf,
    encoder: openh264::encoder::Encoder,
    writer: Option<mp4::Mp4Writer<BufWriter<File>>>,
    size: (u32, u32),
    frame_ticks: u32,
    frames: u64,
    started: bool,
    done: bool,
}

impl Mp4Encoder {
    /// Starts `path` for frames shown at `fps` a second.
    pub fn create(path: &Path, fps: f64) -> Result<Self> {
        if !(fps.is_finite() && fps > 0.0 && fps <= 1000.0) {
            return Err(Error::invalid(
                "frame rate",
                format!("{fps}: must be in (0, 1000]"),
            ));
        }
        if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
        }
        let (file, tmp) = arkit_core::atomic_file::create_temporary(path)?;
        let config = mp4::Mp4Config {
            major_brand: str::parse("isom").expect("fourcc"),
            minor_version: 512,
            compatible_brands: ["isom", "iso2", "avc1", "mp41"]
                .iter()
                .map(|b| str::parse(b).expect("fourcc"))
                .collect(),
            timescale: TIMESCALE,
        };
        let writer = mp4::Mp4Writer::write_start(BufWriter::new(file), &config)
            .map_err(|e| Error::invalid(path.display().to_string(), e.to_string()))?;
        // No rate control: every frame is coded (none skipped), at a fixed quality.
        use openh264::encoder::{EncoderConfig, FrameRate, QpRange, RateControlMode};
        let config = EncoderConfig::new()
            .max_frame_rate(FrameRate::from_hz(fps as f32))
            .rate_control_mode(RateControlMode::Off)
            .qp(QpRange::new(22, 30))
            .skip_frames(false);
        let encoder = openh264::encoder::Encoder::with_api_config(
            openh264::OpenH264API::from_source(),
            config,
        )
        .map_err(|e| Error::invalid("H.264 encoder", e.to_string()))?;
        Ok(Mp4Encoder {
            path: path.to_path_buf(),
            tmp,
            encoder,
            writer: Some(writer),
            size: (0, 0),
            frame_ticks: (TIMESCALE as f64 / fps).round().max(1.0) as u32,
            frames: 0,
            started: false,
            done: false,
        })
    }

    /// Frames written so far.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// Appends a frame.
    pub fn push(&mut self, image: &RgbImage) -> Result<()> {
        let (w, h) = (image.width() & !1, image.height() & !1);
        if w == 0 || h == 0 {
            return Err(Error::invalid(
                self.path.display().to_string(),
                "a frame of an MP4 needs at least 2x2 pixels",
            ));
        }
        if self.frames == 0 {
            self.size = (w, h);
        } else if (w, h) != self.size {
            return Err(Error::invalid(
                self.path.display().to_string(),
                format!(
                    "frame {} is {}x{}, the first was {}x{}: every frame of a video has one size",
                    self.frames, w, h, self.size.0, self.size.1
                ),
            ));
        }
        let even;
        let image = if (w, h) == image.dimensions() {
            image
        } else {
            even = image::imageops::crop_imm(image, 0, 0, w, h).to_image();
            &even
        };
        let yuv = openh264::formats::YUVBuffer::from_rgb8_source(
            openh264::formats::RgbSliceU8::new(image.as_raw(), (w as usize, h as usize)),
        );
        let stream = self
            .encoder
            .encode(&yuv)
            .map_err(|e| Error::invalid("H.264 encoder", e.to_string()))?;
        let is_sync = matches!(stream.frame_type(), openh264::encoder::FrameType::IDR);
        let annex_b = stream.to_vec();
        let (mut sps, mut pps, mut sample) = (None, None, Vec::new());
        for nal in openh264::nal_units(&annex_b) {
            let body = strip_start_code(nal);
            let Some(&first) = body.first() else { continue };
            match first & 0x1f {
                7 => sps = Some(body.to_vec()),
                8 => pps = Some(body.to_vec()),
                _ => {
                    sample.extend_from_slice(&(body.len() as u32).to_be_bytes());
                    sample.extend_from_slice(body);
                }
            }
        }
        let writer = self.writer.as_mut().expect("open until finish");
        let fail = |e: mp4::Error| Error::invalid(self.path.display().to_string(), e.to_string());
        if !self.started {
            let (Some(sps), Some(pps)) = (sps, pps) else {
                return Err(Error::invalid(
                    "H.264 encoder",
                    "its first frame carried no SPS/PPS",
                ));
            };
            writer
                .add_track(&mp4::TrackConfig {
                    track_type: mp4::TrackType::Video,
                    timescale: TIMESCALE,
                    language: "und".into(),
                    media_conf: mp4::MediaConfig::AvcConfig(mp4::AvcConfig {
                        width: w as u16,
                        height: h as u16,
                        seq_param_set: sps,
                        pic_param_set: pps,
                    }),
                })
                .map_err(fail)?;
            self.started = true;
        }
        if !sample.is_empty() {
            writer
                .write_sample(
                    1,
                    &mp4::Mp4Sample {
                        start_time: self.frames * self.frame_ticks as u64,
                        duration: self.frame_ticks,
                        rendering_offset: 0,
                        is_sync,
                        bytes: sample.into(),
                    },
                )
                .map_err(fail)?;
        }
        self.frames += 1;
        Ok(())
    }

    /// Writes the index and renames the file into place.
    pub fn finish(mut self) -> Result<()> {
        let mut writer = self.writer.take().expect("open until finish");
        if self.frames == 0 {
            return Err(Error::invalid(
                self.path.display().to_string(),
                "no frame to write",
            ));
        }
        writer
            .write_end()
            .map_err(|e| Error::invalid(self.path.display().to_string(), e.to_string()))?;
        let file = writer
            .into_writer()
            .into_inner()
            .map_err(|e| Error::io(&self.path, e.into_error()))?;
        arkit_core::atomic_file::publish(&file, &self.tmp, &self.path)?;
        self.done = true;
        Ok(())
    }
}

impl Drop for Mp4Encoder {
    fn drop(&mut self) {
        if !self.done {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

fn strip_start_code(nal: &[u8]) -> &[u8] {
    if nal.starts_with(&[0, 0, 0, 1]) {
        &nal[4..]
    } else if nal.starts_with(&[0, 0, 1]) {
        &nal[3..]
    } else {
        nal
    }
}
