//! `source`: a video's frames, decoded one at a time.
//!
//! Two kinds of input: an MP4 or MOV file with an H.264 (`avc1`) video track, as phones
//! and webcams record them, decoded by OpenH264 (built from source with the crate); and
//! a folder of numbered frames (PNG, JPEG or WebP, ordered by the number in the name).
//! A file with another codec (HEVC, VP9, AV1, ProRes, ...) is refused with an error
//! that names the codec and gives an ffmpeg command that converts it.
//!
//! Frames are decoded as a stream: the file's sample table is read up front (a few
//! bytes a frame), then each sample is read and decoded when its frame is asked for;
//! the decoder keeps its few reference pictures and hands each frame on as it comes
//! out ([`VideoSource::max_frames_held`] counts the most held at once), whatever the
//! video's length. A track's rotation (a portrait phone video is
//! stored landscape with a 90 degree rotation in its header) is applied, so frames are
//! upright as players show them.

use arkit_core::{Error, Result};
use image::RgbImage;
use std::collections::{BinaryHeap, VecDeque};
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

/// One decoded frame.
#[derive(Clone, Debug)]
pub struct Frame {
    /// 0, 1, 2, ... in display order.
    pub index: u64,
    /// Presentation time, seconds from the start.
    pub time_s: f64,
    /// The picture, upright.
    pub image: RgbImage,
}

/// A video's frames, in display order (see the module docs).
pub struct VideoSource {
    kind: Kind,
    next_index: u64,
    max_held: usize,
    skipped: Vec<(String, String)>,
}

enum Kind {
    Folder { files: Vec<PathBuf>, fps: f64 },
    Mp4(Box<Mp4Frames>),
}

struct Mp4Frames {
    path: PathBuf,
    reader: mp4::Mp4Reader<BufReader<File>>,
    track: u32,
    samples: u32,
    next_sample: u32,
    timescale: f64,
    fps: f64,
    length_size: usize,
    /// SPS and PPS in Annex B, fed before the first sample.
    header: Vec<u8>,
    decoder: openh264::decoder::Decoder,
    /// Presentation times of samples given to the decoder and not yet out of it.
    times: BinaryHeap<std::cmp::Reverse<i64>>,
    pending: VecDeque<(i64, RgbImage)>,
    rotation: u32,
    flushed: bool,
}

/// The codec an MP4/MOV sample entry's four characters stand for.
pub fn codec_name(fourcc: &[u8; 4]) -> String {
    let name = match fourcc {
        b"avc1" | b"avc3" => "H.264",
        b"hvc1" | b"hev1" | b"dvh1" | b"dvhe" => "HEVC (H.265)",
        b"vp08" => "VP8",
        b"vp09" => "VP9",
        b"av01" => "AV1",
        b"mp4v" => "MPEG-4 Part 2",
        b"jpeg" | b"mjpa" | b"mjpb" => "Motion JPEG",
        b"apch" | b"apcn" | b"apcs" | b"apco" | b"ap4h" | b"ap4x" => "Apple ProRes",
        b"s263" | b"h263" => "H.263",
        _ => "",
    };
    let code = String::from_utf8_lossy(fourcc).to_string();
    if name.is_empty() {
        format!("'{code}'")
    } else {
        format!("{name} ('{code}')")
    }
}

/// The sample-entry codes of the video tracks of an MP4/MOV file (`b"avc1"` for
/// H.264), read from its `moov` box without decoding anything.
pub fn video_codecs(path: &Path) -> Result<Vec<[u8; 4]>> {
    let mut file = File::open(path).map_err(|e| Error::io(path, e))?;
    let len = file.metadata().map_err(|e| Error::io(path, e))?.len();
    let not_mp4 = || Error::format(path, "not an MP4 or MOV file (no readable 'moov' box)");
    let moov = find_box(&mut file, 0, len, b"moov")
        .map_err(|e| Error::io(path, e))?
        .ok_or_else(not_mp4)?;
    let mut out = Vec::new();
    let mut at = moov.0;
    while at + 8 <= moov.1 {
        let Some((kind, start, end)) =
            box_at(&mut file, at, moov.1).map_err(|e| Error::io(path, e))?
        else {
            break;
        };
        if &kind == b"trak"
            && let Some(code) =
                trak_video_codec(&mut file, start, end).map_err(|e| Error::io(path, e))?
        {
            out.push(code);
        }
        at = end;
    }
    Ok(out)
}

/// The box at `at` (before `limit`): its type and its content's start and end.
fn box_at(f: &mut File, at: u64, limit: u64) -> std::io::Result<Option<([u8; 4], u64, u64)>> {
    let mut head = [0u8; 8];
    f.seek(SeekFrom::Start(at))?;
    if f.read_exact(&mut head).is_err() {
        return Ok(None);
    }
    let size32 = u32::from_be_bytes(head[..4].try_into().expect("4 bytes")) as u64;
    let kind: [u8; 4] = head[4..].try_into().expect("4 bytes");
    let (start, size) = match size32 {
        1 => {
            let mut big = [0u8; 8];
            f.read_exact(&mut big)?;
            (at + 16, u64::from_be_bytes(big))
        }
        0 => (at + 8, limit - at),
        s => (at + 8, s),
    };
    let end = at.saturating_add(size);
    if size < 8 || end > limit || start > end {
        return Ok(None);
    }
    Ok(Some((kind, start, end)))
}

/// The content range of the first box of type `kind` in `[from, to)`.
fn find_box(
    f: &mut File,
    from: u64,
    to: u64,
    kind: &[u8; 4],
) -> std::io::Result<Option<(u64, u64)>> {
    let mut at = from;
    while at + 8 <= to {
        let Some((k, start, end)) = box_at(f, at, to)? else {
            return Ok(None);
        };
        if &k == kind {
            return Ok(Some((start, end)));
        }
        at = end;
    }
    Ok(None)
}

/// A `trak`'s first sample-entry code when its handler is video (`vide`).
fn trak_video_codec(f: &mut File, start: u64, end: u64) -> std::io::Result<Option<[u8; 4]>> {
    let Some(mdia) = find_box(f, start, end, b"mdia")? else {
        return Ok(None);
    };
    let Some(hdlr) = find_box(f, mdia.0, mdia.1, b"hdlr")? else {
        return Ok(None);
    };
    // version/flags (4), pre_defined (4), handler_type (4).
    let mut h = [0u8; 12];
    f.seek(SeekFrom::Start(hdlr.0))?;
    f.read_exact(&mut h)?;
    if &h[8..12] != b"vide" {
        return Ok(None);
    }
    let Some(minf) = find_box(f, mdia.0, mdia.1, b"minf")? else {
        return Ok(None);
    };
    let Some(stbl) = find_box(f, minf.0, minf.1, b"stbl")? else {
        return Ok(None);
    };
    let Some(stsd) = find_box(f, stbl.0, stbl.1, b"stsd")? else {
        return Ok(None);
    };
    // version/flags (4), entry count (4), then the first entry's size (4) and type (4).
    let mut e = [0u8; 16];
    f.seek(SeekFrom::Start(stsd.0))?;
    f.read_exact(&mut e)?;
    Ok(Some(e[12..16].try_into().expect("4 bytes")))
}

/// The number in a frame file's name (its last run of digits), for ordering.
fn frame_number(path: &Path) -> Option<u64> {
    let stem = path.file_stem()?.to_string_lossy().to_string();
    let digits: String = stem
        .chars()
        .rev()
        .skip_while(|c| !c.is_ascii_digit())
        .take_while(|c| c.is_ascii_digit())
        .collect();
    digits.chars().rev().collect::<String>().parse().ok()
}

impl VideoSource {
    /// Opens an MP4/MOV file or a folder of numbered frames (played at `folder_fps`).
    pub fn open(path: &Path, folder_fps: f64) -> Result<Self> {
        let meta = std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
        let kind = if meta.is_dir() {
            Kind::Folder {
                files: numbered_frames(path)?,
                fps: folder_fps,
            }
        } else {
            Kind::Mp4(Box::new(Mp4Frames::open(path)?))
        };
        if !(folder_fps.is_finite() && folder_fps > 0.0) {
            return Err(Error::invalid(
                "--fps",
                format!("{folder_fps}: must be > 0"),
            ));
        }
        Ok(VideoSource {
            kind,
            next_index: 0,
            max_held: 0,
            skipped: Vec::new(),
        })
    }

    /// The number of frames (from the file's sample table, or the folder's files).
    pub fn frame_count(&self) -> u64 {
        match &self.kind {
            Kind::Folder { files, .. } => files.len() as u64,
            Kind::Mp4(m) => m.samples as u64,
        }
    }

    /// Frames a second (the file's average, or the folder's given rate).
    pub fn fps(&self) -> f64 {
        match &self.kind {
            Kind::Folder { fps, .. } => *fps,
            Kind::Mp4(m) => m.fps,
        }
    }

    /// The most decoded frames held at once so far (decoded and not yet returned, plus the one returned).
    pub fn max_frames_held(&self) -> usize {
        self.max_held
    }

    /// What was opened, for messages: "H.264 1920x1080" or "folder of 120 frames".
    pub fn describe(&self) -> String {
        match &self.kind {
            Kind::Folder { files, fps } => {
                format!("a folder of {} frames at {fps} fps", files.len())
            }
            Kind::Mp4(m) => format!("H.264, {} frames at {:.2} fps", m.samples, m.fps),
        }
    }

    /// The frames skipped so far, each with why: a frame file that could not be read
    /// (named by its path), or an H.264 sample the decoder refused (named by its number).
    pub fn skipped(&self) -> &[(String, String)] {
        &self.skipped
    }

    /// The next frame, or `None` at the end. A frame file that cannot be read, or a
    /// sample the decoder refuses, is skipped and listed in [`Self::skipped`]; a
    /// folder's frame keeps its place (index and time) in the folder.
    pub fn next_frame(&mut self) -> Result<Option<Frame>> {
        let frame = match &mut self.kind {
            Kind::Folder { files, fps } => loop {
                let index = self.next_index;
                let Some(path) = files.get(index as usize) else {
                    return Ok(None);
                };
                self.next_index += 1;
                match crate::picture::read_rgb8_checked(path, |_| Ok(())) {
                    Ok(image) => {
                        self.max_held = self.max_held.max(1);
                        return Ok(Some(Frame {
                            index,
                            time_s: index as f64 / *fps,
                            image,
                        }));
                    }
                    Err(e) => self
                        .skipped
                        .push((path.display().to_string(), e.to_string())),
                }
            },
            Kind::Mp4(m) => {
                let index = self.next_index;
                let got = m.next(&mut self.skipped)?;
                self.max_held = self.max_held.max(m.pending.len() + got.is_some() as usize);
                got.map(|(t, image)| Frame {
                    index,
                    time_s: t,
                    image,
                })
            }
        };
        if frame.is_some() {
            self.next_index += 1;
        }
        Ok(frame)
    }
}

/// A folder's frame files, ordered by their number.
fn numbered_frames(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut files: Vec<(u64, PathBuf)> = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))? {
        let p = entry.map_err(|e| Error::io(dir, e))?.path();
        let is_image = p.is_file()
            && p.extension().is_some_and(|x| {
                matches!(
                    x.to_string_lossy().to_ascii_lowercase().as_str(),
                    "png" | "jpg" | "jpeg" | "webp"
                )
            });
        if !is_image {
            continue;
        }
        let n = frame_number(&p).ok_or_else(|| {
            Error::format(
                &p,
                "a frame file of a video folder needs a number in its name (frame-000017.png)",
            )
        })?;
        files.push((n, p));
    }
    if files.is_empty() {
        return Err(Error::format(
            dir,
            "a folder of video frames with no .png, .jpg, .jpeg or .webp file",
        ));
    }
    files.sort();
    if let Some(w) = files.windows(2).find(|w| w[0].0 == w[1].0) {
        return Err(Error::format(
            dir,
            format!(
                "{} and {} have the same frame number {}",
                w[0].1.display(),
                w[1].1.display(),
                w[0].0
            ),
        ));
    }
    Ok(files.into_iter().map(|(_, p)| p).collect())
}

/// The ffmpeg command that turns `path` into an H.264 MP4 that arkit-tool reads.
pub fn convert_hint(path: &Path) -> String {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().to_string())
        .unwrap_or_else(|| "video".into());
    format!(
        "convert it to H.264 first: ffmpeg -i '{}' -c:v libx264 -pix_fmt yuv420p -an '{}-h264.mp4'",
        path.display(),
        stem
    )
}

impl Mp4Frames {
    fn open(path: &Path) -> Result<Self> {
        let codecs = video_codecs(path)?;
        let Some(code) = codecs.first() else {
            return Err(Error::format(path, "has no video track"));
        };
        if code != b"avc1" {
            return Err(Error::format(
                path,
                format!(
                    "its video is {}: arkit-tool decodes H.264 ('avc1') only; {}",
                    codec_name(code),
                    convert_hint(path)
                ),
            ));
        }
        let file = File::open(path).map_err(|e| Error::io(path, e))?;
        let len = file.metadata().map_err(|e| Error::io(path, e))?.len();
        let reader = mp4::Mp4Reader::read_header(BufReader::new(file), len)
            .map_err(|e| Error::format(path, format!("not a readable MP4/MOV: {e}")))?;
        let track = reader
            .tracks()
            .values()
            .filter(|t| t.trak.mdia.minf.stbl.stsd.avc1.is_some())
            .map(|t| t.track_id())
            .min()
            .ok_or_else(|| Error::format(path, "has no H.264 video track"))?;
        let t = &reader.tracks()[&track];
        let avc1 = t.trak.mdia.minf.stbl.stsd.avc1.as_ref().expect("filtered");
        let avcc = &avc1.avcc;
        let mut header = Vec::new();
        for nal in avcc
            .sequence_parameter_sets
            .iter()
            .chain(&avcc.picture_parameter_sets)
        {
            header.extend_from_slice(&[0, 0, 0, 1]);
            header.extend_from_slice(&nal.bytes);
        }
        let samples = t.sample_count();
        let timescale = t.timescale().max(1) as f64;
        let duration_s = t.trak.mdia.mdhd.duration as f64 / timescale;
        let fps = if duration_s > 0.0 && samples > 0 {
            samples as f64 / duration_s
        } else {
            30.0
        };
        let m = &t.trak.tkhd.matrix;
        let angle = (m.b as f64).atan2(m.a as f64).to_degrees();
        let rotation = (((angle / 90.0).round() as i64).rem_euclid(4) * 90) as u32;
        let decoder = openh264::decoder::Decoder::new()
            .map_err(|e| Error::invalid("H.264 decoder", e.to_string()))?;
        Ok(Mp4Frames {
            path: path.to_path_buf(),
            length_size: avcc.length_size_minus_one as usize % 4 + 1,
            reader,
            track,
            samples,
            next_sample: 1,
            timescale,
            fps,
            header,
            decoder,
            times: BinaryHeap::new(),
            pending: VecDeque::new(),
            rotation,
            flushed: false,
        })
    }

    /// The next frame in display order, with its time in seconds; a sample the decoder
    /// refuses is listed in `skipped` and left out.
    fn next(&mut self, skipped: &mut Vec<(String, String)>) -> Result<Option<(f64, RgbImage)>> {
        while self.pending.is_empty() && !self.flushed {
            if self.next_sample > self.samples {
                let frames = self.decoder.flush_remaining().map_err(|e| {
                    Error::format(&self.path, format!("H.264 decoding at the end: {e}"))
                })?;
                let images: Vec<RgbImage> = frames.iter().map(rgb_image).collect();
                for image in images {
                    let t = self.times.pop().map(|r| r.0).unwrap_or(0);
                    self.pending.push_back((t, image));
                }
                self.flushed = true;
                break;
            }
            let id = self.next_sample;
            self.next_sample += 1;
            let sample = self
                .reader
                .read_sample(self.track, id)
                .map_err(|e| Error::format(&self.path, format!("frame sample {id}: {e}")))?;
            let Some(sample) = sample else { continue };
            let pts = sample.start_time as i64 + sample.rendering_offset as i64;
            self.times.push(std::cmp::Reverse(pts));
            let mut packet = if id == 1 {
                self.header.clone()
            } else {
                Vec::new()
            };
            let mut rest: &[u8] = &sample.bytes;
            while rest.len() >= self.length_size {
                let mut n = 0usize;
                for &b in &rest[..self.length_size] {
                    n = n << 8 | b as usize;
                }
                rest = &rest[self.length_size..];
                if n > rest.len() {
                    return Err(Error::format(
                        &self.path,
                        format!("frame sample {id}: a NAL unit runs past the sample's end"),
                    ));
                }
                packet.extend_from_slice(&[0, 0, 0, 1]);
                packet.extend_from_slice(&rest[..n]);
                rest = &rest[n..];
            }
            match self.decoder.decode(&packet) {
                Ok(Some(yuv)) => {
                    let image = rgb_image(&yuv);
                    let t = self.times.pop().map(|r| r.0).unwrap_or(0);
                    self.pending.push_back((t, image));
                }
                Ok(None) => {}
                Err(e) => {
                    skipped.push((
                        format!("{} (sample {id})", self.path.display()),
                        format!("H.264: {e}"),
                    ));
                    self.times.retain(|r| r.0 != pts);
                }
            }
        }
        Ok(self.pending.pop_front().map(|(t, image)| {
            let image = match self.rotation {
                90 => image::imageops::rotate90(&image),
                180 => image::imageops::rotate180(&image),
                270 => image::imageops::rotate270(&image),
                _ => image,
            };
            (t as f64 / self.timescale, image)
        }))
    }
}

fn rgb_image(yuv: &openh264::decoder::DecodedYUV<'_>) -> RgbImage {
    use openh264::formats::YUVSource;
    let (w, h) = yuv.dimensions();
    let mut buf = vec![0u8; w * h * 3];
    yuv.write_rgb8(&mut buf);
    RgbImage::from_raw(w as u32, h as u32, buf).expect("w * h * 3 bytes")
}
