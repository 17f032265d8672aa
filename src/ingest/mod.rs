//! Ingest: from a clinical CT to the mechanical model: lung segmentation, cubic elements and
//! anatomical constraint groups.

mod cancel;
pub mod four_dct;
pub mod lung_model;
pub mod pipeline;
pub mod scan;
pub mod segmentation;
pub mod stored;

pub use cancel::Cancel;
pub use pipeline::{ingest_scan, IngestOutcome, IngestSettings, IngestSummary};
pub use scan::{load_ct, load_ct_with, LoadedScan, ScanFormat};
