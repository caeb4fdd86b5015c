//! What the subcommands set up before they work: the topology, the thread pool and
//! the network's settings.

#[cfg(feature = "model")]
use arkit_core::Error;
use arkit_core::Result;
#[cfg(feature = "model")]
use arkit_perspnet::PerspNetConfig;

/// Reads the topology named by `--resources` (or the built-in face without it).
pub(super) fn load_topology(
    resources: Option<&std::path::Path>,
) -> Result<arkit_data::mesh::FaceTopology> {
    match resources {
        Some(dir) => arkit_data::mesh::FaceTopology::from_resources(dir),
        None => Ok(arkit_data::mesh::builtin().topology.clone()),
    }
}

/// A rayon pool of `jobs` threads (all cores when `None`; `--jobs` is 1..=1024).
pub(super) fn thread_pool(jobs: Option<usize>) -> Result<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(jobs.unwrap_or(0))
        .build()
        .map_err(|e| arkit_core::Error::invalid("--jobs", e.to_string()))
}

/// The network settings named by `--config`.
#[cfg(feature = "model")]
pub(super) fn config_named(name: &str) -> Result<PerspNetConfig> {
    match name {
        "tiny" => Ok(PerspNetConfig::tiny()),
        "paper" => Ok(PerspNetConfig::paper()),
        path => {
            let p = std::path::Path::new(path);
            let text = std::fs::read_to_string(p).map_err(|e| Error::io(p, e))?;
            let c: PerspNetConfig =
                serde_json::from_str(&text).map_err(|e| Error::format(p, e.to_string()))?;
            c.validate().map_err(|e| Error::format(p, e))?;
            Ok(c)
        }
    }
}
