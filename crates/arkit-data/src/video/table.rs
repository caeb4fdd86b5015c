//! `table`: `predict --video`'s rows (one per frame and track) written as JSON lines,
//! CSV or Parquet (by the file's extension), streamed to a temporary file and renamed
//! into place when the run ends (Parquet's rows are held until then: a few hundred
//! bytes each).

use arkit_core::{Error, Result};
use polars::prelude::{Column, DataFrame};
use serde_json::json;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// The pose of a face on a frame.
#[derive(Clone, Debug, PartialEq)]
pub struct RowPose {
    /// The release's `R_t` (row vectors, OpenGL camera), row-major 4x4.
    pub r_t: [f64; 16],
    /// Yaw, pitch and roll (or the convention's three angles) of `r_t`.
    pub angles: [f64; 3],
    /// The translation, metres (release frame).
    pub translation_m: [f64; 3],
    /// OpenCV's rotation vector and translation (metres).
    pub rvec: [f64; 3],
    /// OpenCV's translation, metres.
    pub tvec_m: [f64; 3],
    /// The angles of the unsmoothed pose (equal to `angles` without smoothing).
    pub raw_angles: [f64; 3],
    /// RANSAC's inliers.
    pub inliers: usize,
    /// The distinct points given to PnP.
    pub points: usize,
}

/// One face on one frame.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameRow {
    /// The frame's index (0, 1, ... in display order).
    pub frame: u64,
    /// The frame's time, seconds.
    pub time_s: f64,
    /// The track's id.
    pub track: u64,
    /// Whether the detector (or the boxes file) gave the box on this frame.
    pub detected: bool,
    /// The face box, pixels.
    pub bbox: [f64; 4],
    /// The pose, `None` when PnP failed.
    pub pose: Option<RowPose>,
}

/// Writes rows to a `.jsonl`, `.csv` or `.parquet` file.
pub struct RowWriter {
    path: PathBuf,
    tmp: PathBuf,
    names: [&'static str; 3],
    kind: Kind,
    done: bool,
}

enum Kind {
    Jsonl(BufWriter<File>),
    Csv(BufWriter<File>),
    Parquet(Vec<FrameRow>),
}

impl RowWriter {
    /// Starts `path`; the angle columns are named `names` (e.g. yaw, pitch, roll).
    pub fn create(path: &Path, names: [&'static str; 3]) -> Result<Self> {
        let ext = path
            .extension()
            .map(|x| x.to_string_lossy().to_ascii_lowercase())
            .unwrap_or_default();
        if !matches!(ext.as_str(), "jsonl" | "csv" | "parquet") {
            return Err(Error::invalid(
                "--output",
                format!(
                    "{}: the rows of a video go to a .jsonl, .csv or .parquet file",
                    path.display()
                ),
            ));
        }
        if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
        }
        // JSON lines and CSV are streamed into a temporary of their own; Parquet is
        // written at the end (atomically, by `write_parquet`).
        let mut tmp = PathBuf::new();
        let mut open = || -> Result<BufWriter<File>> {
            let (file, t) = arkit_core::atomic_file::create_temporary(path)?;
            tmp = t;
            Ok(BufWriter::new(file))
        };
        let kind = match ext.as_str() {
            "jsonl" => Kind::Jsonl(open()?),
            "csv" => {
                let mut w = open()?;
                w.write_all(csv_header(&names).as_bytes())
                    .map_err(|e| Error::io(path, e))?;
                Kind::Csv(w)
            }
            _ => Kind::Parquet(Vec::new()),
        };
        Ok(RowWriter {
            path: path.to_path_buf(),
            tmp,
            names,
            kind,
            done: false,
        })
    }

    /// Appends a row.
    pub fn push(&mut self, row: &FrameRow) -> Result<()> {
        let path = self.path.clone();
        match &mut self.kind {
            Kind::Jsonl(w) => {
                let line = json_row(row, &self.names).to_string();
                writeln!(w, "{line}").map_err(|e| Error::io(&path, e))
            }
            Kind::Csv(w) => writeln!(w, "{}", csv_row(row)).map_err(|e| Error::io(&path, e)),
            Kind::Parquet(rows) => {
                rows.push(row.clone());
                Ok(())
            }
        }
    }

    /// Finishes the file and renames it into place.
    pub fn finish(mut self) -> Result<()> {
        let kind = std::mem::replace(&mut self.kind, Kind::Parquet(Vec::new()));
        let file = match kind {
            Kind::Jsonl(w) | Kind::Csv(w) => w
                .into_inner()
                .map_err(|e| Error::io(&self.path, e.into_error()))?,
            Kind::Parquet(rows) => {
                let mut df = frame(&rows, &self.names)?;
                crate::store::write_parquet(&self.path, &mut df)?;
                self.done = true;
                return Ok(());
            }
        };
        arkit_core::atomic_file::publish(&file, &self.tmp, &self.path)?;
        self.done = true;
        Ok(())
    }
}

impl Drop for RowWriter {
    fn drop(&mut self) {
        if !self.done && !self.tmp.as_os_str().is_empty() {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// A row as a JSON object (the `.jsonl` line).
pub fn json_row(row: &FrameRow, names: &[&str; 3]) -> serde_json::Value {
    let mut v = json!({
        "frame": row.frame,
        "time_s": row.time_s,
        "track": row.track,
        "detected": row.detected,
        "box": row.bbox,
    });
    match &row.pose {
        None => v["status"] = json!("pnp failed"),
        Some(p) => {
            let rt = &p.r_t;
            v["status"] = json!("ok");
            v["R_t"] = json!([
                [rt[0], rt[1], rt[2], rt[3]],
                [rt[4], rt[5], rt[6], rt[7]],
                [rt[8], rt[9], rt[10], rt[11]],
                [rt[12], rt[13], rt[14], rt[15]]
            ]);
            let a = p.angles;
            let r = p.raw_angles;
            v["angles"] = json!({names[0]: a[0], names[1]: a[1], names[2]: a[2]});
            v["raw_angles"] = json!({names[0]: r[0], names[1]: r[1], names[2]: r[2]});
            v["translation_m"] = json!(p.translation_m);
            v["rvec"] = json!(p.rvec);
            v["tvec_m"] = json!(p.tvec_m);
            v["inliers"] = json!(p.inliers);
            v["distinct_points"] = json!(p.points);
        }
    }
    v
}

fn csv_header(names: &[&str; 3]) -> String {
    let mut h = format!(
        "frame,time_s,track,detected,x0,y0,x1,y1,status,{0},{1},{2},raw_{0},raw_{1},raw_{2},tx_m,ty_m,tz_m,rvec_x,rvec_y,rvec_z,tvec_x_m,tvec_y_m,tvec_z_m,inliers,distinct_points",
        names[0], names[1], names[2]
    );
    for i in 0..16 {
        h.push_str(&format!(",r_t_{}{}", i / 4, i % 4));
    }
    h.push('\n');
    h
}

fn csv_row(row: &FrameRow) -> String {
    let mut cells = vec![
        row.frame.to_string(),
        row.time_s.to_string(),
        row.track.to_string(),
        row.detected.to_string(),
    ];
    cells.extend(row.bbox.iter().map(f64::to_string));
    match &row.pose {
        None => {
            cells.push("pnp failed".into());
            cells.extend(std::iter::repeat_n(String::new(), 3 * 5 + 2 + 16));
        }
        Some(p) => {
            cells.push("ok".into());
            for v in [p.angles, p.raw_angles, p.translation_m, p.rvec, p.tvec_m] {
                cells.extend(v.iter().map(f64::to_string));
            }
            cells.extend([p.inliers.to_string(), p.points.to_string()]);
            cells.extend(p.r_t.iter().map(f64::to_string));
        }
    }
    cells.join(",")
}

/// The rows as a table with the CSV's columns.
fn frame(rows: &[FrameRow], names: &[&str; 3]) -> Result<DataFrame> {
    let mut columns = vec![
        Column::new(
            "frame".into(),
            rows.iter().map(|r| r.frame).collect::<Vec<u64>>(),
        ),
        Column::new(
            "time_s".into(),
            rows.iter().map(|r| r.time_s).collect::<Vec<f64>>(),
        ),
        Column::new(
            "track".into(),
            rows.iter().map(|r| r.track).collect::<Vec<u64>>(),
        ),
        Column::new(
            "detected".into(),
            rows.iter().map(|r| r.detected).collect::<Vec<bool>>(),
        ),
    ];
    for (i, n) in ["x0", "y0", "x1", "y1"].iter().enumerate() {
        columns.push(Column::new(
            (*n).into(),
            rows.iter().map(|r| r.bbox[i]).collect::<Vec<f64>>(),
        ));
    }
    columns.push(Column::new(
        "status".into(),
        rows.iter()
            .map(|r| if r.pose.is_some() { "ok" } else { "pnp failed" })
            .collect::<Vec<&str>>(),
    ));
    let mut pose_col = |name: String, f: &dyn Fn(&RowPose) -> f64| {
        columns.push(Column::new(
            name.into(),
            rows.iter()
                .map(|r| r.pose.as_ref().map(f))
                .collect::<Vec<Option<f64>>>(),
        ));
    };
    for (i, n) in names.iter().enumerate() {
        pose_col(n.to_string(), &|p| p.angles[i]);
    }
    for (i, n) in names.iter().enumerate() {
        pose_col(format!("raw_{n}"), &|p| p.raw_angles[i]);
    }
    for (i, n) in ["tx_m", "ty_m", "tz_m"].iter().enumerate() {
        pose_col(n.to_string(), &|p| p.translation_m[i]);
    }
    for (i, n) in ["rvec_x", "rvec_y", "rvec_z"].iter().enumerate() {
        pose_col(n.to_string(), &|p| p.rvec[i]);
    }
    for (i, n) in ["tvec_x_m", "tvec_y_m", "tvec_z_m"].iter().enumerate() {
        pose_col(n.to_string(), &|p| p.tvec_m[i]);
    }
    for i in 0..16 {
        pose_col(format!("r_t_{}{}", i / 4, i % 4), &|p| p.r_t[i]);
    }
    columns.push(Column::new(
        "inliers".into(),
        rows.iter()
            .map(|r| r.pose.as_ref().map(|p| p.inliers as u32))
            .collect::<Vec<Option<u32>>>(),
    ));
    columns.push(Column::new(
        "distinct_points".into(),
        rows.iter()
            .map(|r| r.pose.as_ref().map(|p| p.points as u32))
            .collect::<Vec<Option<u32>>>(),
    ));
    DataFrame::new(rows.len(), columns).map_err(|e| Error::invalid("video rows", e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rows() -> Vec<FrameRow> {
        let pose = RowPose {
            r_t: std::array::from_fn(|i| i as f64),
            angles: [1.0, 2.0, 3.0],
            translation_m: [0.1, 0.2, -0.5],
            rvec: [0.0, 0.1, 0.2],
            tvec_m: [0.1, -0.2, 0.5],
            raw_angles: [1.5, 2.0, 3.0],
            inliers: 80,
            points: 100,
        };
        vec![
            FrameRow {
                frame: 0,
                time_s: 0.0,
                track: 0,
                detected: true,
                bbox: [1.0, 2.0, 30.0, 40.0],
                pose: Some(pose),
            },
            FrameRow {
                frame: 1,
                time_s: 1.0 / 30.0,
                track: 3,
                detected: false,
                bbox: [2.0, 2.0, 31.0, 40.0],
                pose: None,
            },
        ]
    }

    #[test]
    fn the_three_formats_hold_the_same_rows() {
        let dir = tempfile::tempdir().unwrap();
        let names = ["yaw", "pitch", "roll"];
        for ext in ["jsonl", "csv", "parquet"] {
            let path = dir.path().join(format!("rows.{ext}"));
            let mut w = RowWriter::create(&path, names).unwrap();
            for r in rows() {
                w.push(&r).unwrap();
            }
            w.finish().unwrap();
            let left: Vec<_> = std::fs::read_dir(dir.path())
                .unwrap()
                .flatten()
                .filter(|e| {
                    arkit_core::atomic_file::is_temporary_name(&e.file_name().to_string_lossy())
                })
                .collect();
            assert!(left.is_empty(), "{left:?}");
            match ext {
                "jsonl" => {
                    let text = std::fs::read_to_string(&path).unwrap();
                    let lines: Vec<serde_json::Value> = text
                        .lines()
                        .map(|l| serde_json::from_str(l).unwrap())
                        .collect();
                    assert_eq!(lines.len(), 2);
                    assert_eq!(lines[0]["angles"]["pitch"], 2.0);
                    assert_eq!(lines[0]["R_t"][3][1], 13.0);
                    assert_eq!(lines[1]["status"], "pnp failed");
                    assert_eq!(lines[1]["track"], 3);
                }
                "csv" => {
                    let text = std::fs::read_to_string(&path).unwrap();
                    let lines: Vec<&str> = text.lines().collect();
                    let header: Vec<&str> = lines[0].split(',').collect();
                    for l in &lines[1..] {
                        assert_eq!(l.split(',').count(), header.len(), "{l}");
                    }
                    let yaw = header.iter().position(|h| *h == "yaw").unwrap();
                    assert_eq!(lines[1].split(',').nth(yaw), Some("1"));
                }
                _ => {
                    let df = crate::store::read_parquet(&path).unwrap();
                    assert_eq!(df.height(), 2);
                    let roll = crate::store::f64_values(&df, "roll", &path).unwrap();
                    assert_eq!(roll[0], 3.0);
                    assert!(roll[1].is_nan());
                }
            }
        }
        assert!(RowWriter::create(&dir.path().join("rows.txt"), names).is_err());
    }
}
