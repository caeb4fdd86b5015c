//! `arkit-tool topology`.

use arkit_core::Result;
use arkit_data::mesh::nearest_mirror_partners;
use clap::Args;
use serde_json::json;
use std::path::PathBuf;
use std::process::ExitCode;

/// Describe a face topology: counts, boundary loops, hole fill and mirror symmetry.
///
/// Without --resources it describes the built-in synthetic face (a stand-in, not
/// Apple's mesh); with it, the release's files in that folder.
///
/// Example: arkit-tool topology --resources ../shared/arkitface-resources --json
#[derive(Args, Debug)]
pub struct TopologyArgs {
    /// Folder with triangles.npy, uv_coords_std_202109.npy, kpt_ind.npy (and optionally template_verts.npy).
    #[arg(long)]
    resources: Option<PathBuf>,
    /// Write the template face as an OBJ file.
    #[arg(long, value_name = "FILE.obj")]
    obj: Option<PathBuf>,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: TopologyArgs) -> Result<ExitCode> {
    let topo = super::setup::load_topology(a.resources.as_deref())?;
    let loops = topo.boundary_loops()?;
    let fill = topo.hole_fill()?;
    let mirror_map = topo.mirror_map()?;
    let mirror = topo.template.as_ref().map(|t| nearest_mirror_partners(t));
    let self_mirrored = (0..topo.vertex_count)
        .filter(|&i| mirror_map[i] as usize == i)
        .count();
    let loop_list: Vec<_> = loops
        .loops
        .iter()
        .map(|(role, l)| json!({"role": format!("{role:?}"), "vertices": l.len()}))
        .collect();
    let report = json!({
        "source": topo.source,
        "vertices": topo.vertex_count,
        "triangles": topo.triangles.len(),
        "landmarks": topo.landmarks.len(),
        "boundary_loops": loop_list,
        "boundary_edges": loops.edge_count(),
        "hole_fill_triangles": fill.triangles.len(),
        "mirror_self_mapped_vertices": self_mirrored,
        "template_asymmetry_max_m": mirror.as_ref().map(|m| m.1),
    });
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report).expect("json"));
    } else {
        println!("{}", topo.source);
        println!(
            "  {} vertices, {} triangles, {} landmarks",
            topo.vertex_count,
            topo.triangles.len(),
            topo.landmarks.len()
        );
        for (role, l) in &loops.loops {
            println!("  boundary loop {role:?}: {} vertices", l.len());
        }
        println!(
            "  {} boundary edges; {} triangles fill the eyes and mouth",
            loops.edge_count(),
            fill.triangles.len()
        );
        println!("  mirror map (from the UV layout): {self_mirrored} vertices on the centre line");
        if let Some((_, worst)) = mirror {
            println!(
                "  template asymmetry: a mirrored vertex is at most {:.2} mm from its nearest vertex",
                worst * 1000.0
            );
        }
    }
    if let (Some(path), Some(t)) = (&a.obj, &topo.template) {
        topo.write_obj(path, t)?;
    }
    Ok(ExitCode::SUCCESS)
}
