//! Reading a recording back: which entities it holds, how many rows each, on
//! which timelines (for tests and quick checks; the viewer does the rest).

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use anyhow::{Context, Result};
use re_log_encoding::DecoderApp;
use rerun::log::{Chunk, LogMsg};
use rerun::StoreKind;

/// Rows logged to one entity of the recording store.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct EntitySummary {
    /// Rows with a time (one per step for per-step data).
    pub temporal_rows: u64,
    /// Rows of each chunk of temporal rows, in file order (per-step data arrives in
    /// batches).
    pub temporal_chunk_rows: Vec<u64>,
    /// Static rows (geometry, styles).
    pub static_rows: u64,
    /// Component identifiers seen, e.g. `Transform3D:translation`.
    pub components: BTreeSet<String>,
    /// Timelines of the temporal rows.
    pub timelines: BTreeSet<String>,
}

/// Summary of an `.rrd` file.
#[derive(Debug, Clone, Default)]
pub struct RrdSummary {
    /// Recording-store entities by path (`/world/robot/trunk`, ...).
    pub entities: BTreeMap<String, EntitySummary>,
    /// Application ids of all stores.
    pub application_ids: BTreeSet<String>,
    /// Chunks in blueprint stores (a layout was sent with the recording).
    pub blueprint_chunks: usize,
    /// Blueprint activation commands.
    pub blueprint_activations: usize,
    /// Entity paths of the blueprint stores (e.g. `/view/<id>/EyeControls3D`).
    pub blueprint_entities: BTreeSet<String>,
}

impl RrdSummary {
    /// The entity at `path` (with or without the leading `/`).
    pub fn entity(&self, path: &str) -> Option<&EntitySummary> {
        let p = if path.starts_with('/') {
            path.to_string()
        } else {
            format!("/{path}")
        };
        self.entities.get(&p)
    }
}

/// Decodes `path` and counts rows per entity.
pub fn summarize_rrd(path: &Path) -> Result<RrdSummary> {
    let file = std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let decoder = DecoderApp::decode_eager(std::io::BufReader::new(file))
        .with_context(|| format!("{} is not an .rrd file", path.display()))?;
    let mut s = RrdSummary::default();
    for msg in decoder {
        let msg = msg.with_context(|| format!("decoding {}", path.display()))?;
        match msg {
            LogMsg::SetStoreInfo(info) => {
                s.application_ids
                    .insert(info.info.application_id().to_string());
            }
            LogMsg::ArrowMsg(store, arrow) => {
                let chunk = Chunk::from_arrow_msg(&arrow).context("decoding a chunk")?;
                if store.kind() == StoreKind::Blueprint {
                    s.blueprint_chunks += 1;
                    s.blueprint_entities.insert(chunk.entity_path().to_string());
                    continue;
                }
                let e = s
                    .entities
                    .entry(chunk.entity_path().to_string())
                    .or_default();
                let rows = chunk.num_rows() as u64;
                if chunk.is_static() {
                    e.static_rows += rows;
                } else {
                    e.temporal_rows += rows;
                    e.temporal_chunk_rows.push(rows);
                    e.timelines
                        .extend(chunk.timelines().keys().map(|t| t.to_string()));
                }
                e.components.extend(
                    chunk
                        .components()
                        .component_descriptors()
                        .map(|d| d.component.to_string()),
                );
            }
            LogMsg::BlueprintActivationCommand(_) => s.blueprint_activations += 1,
        }
    }
    Ok(s)
}
