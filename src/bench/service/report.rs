//! The service benchmark's Markdown report.

use std::fmt::Write as _;

use super::{
    LoadResult, ServiceBenchReport, BENCH_ELEMENT_SIZE_MM, LOAD_CONCURRENCY, LOAD_WARMUP_S, MIB,
    POLL_INTERVAL_MS, TRACE_DURATION_S, TRACE_RATE_HZ, UPLOAD_SLICES,
};
use crate::bench::{Outcome, TimeStats};
use crate::markdown::{one_line, Table};

impl ServiceBenchReport {
    /// The report as Markdown (tables with units).
    pub fn to_markdown(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "# lungmotion HTTP service benchmark\n");
        let _ = writeln!(
            s,
            "{} UTC, lungmotion {}, {} ({} logical cores); load average at start {}. \
             Server in-process ({} worker, 127.0.0.1, `[run]` at {} mm); **client and server \
             share the {} cores**, so rates are lower bounds for a dedicated server.{}\n",
            self.date_utc,
            self.lungmotion_version,
            self.cpu_model,
            self.cores,
            self.load_average_at_start
                .map_or("unknown".into(), |l| format!(
                    "{:.2} / {:.2} / {:.2}",
                    l[0], l[1], l[2]
                )),
            self.server_workers,
            BENCH_ELEMENT_SIZE_MM,
            self.cores,
            if self.options.quick {
                " Quick mode: one repeat, small slices, short load (numbers indicative only)."
            } else {
                ""
            }
        );
        self.write_uploads(&mut s);
        self.write_overhead(&mut s);
        self.write_load(&mut s);
        self.write_popi(&mut s);
        self.write_queue(&mut s);
        if let Some(p) = self.peak_rss_bytes {
            let _ = writeln!(
                s,
                "\nProcess peak resident memory (VmHWM, client + server + in-process runs): {:.0} MiB.",
                p as f64 / MIB
            );
        }
        s
    }

    fn write_uploads(&self, s: &mut String) {
        let _ = writeln!(s, "## Upload of a {UPLOAD_SLICES}-slice DICOM zip\n");
        let _ = writeln!(
            s,
            "`POST /v1/scans`, body streamed from the zip file (Content-Length set). The series is \
             the phantom CT upsampled (trilinear, same extent) to {UPLOAD_SLICES} slices, int16. \
             *Body sent*: until the client handed over the body's last byte; up to {} of it \
             may then still sit in loopback socket buffers (TCP send + receive maxima), so \
             *MiB/s sent* overstates the receive rate for small zips; *to 201*: includes load + \
             segmentation + meshing + store; *after body* = to 201 − body sent. `load_ct` \
             in-process on the same zip, and the segmentation and model times the 201 reports, \
             split *after body*; *rest* is what remains (the rest of the receive, store, \
             response), so *receive MiB/s ≥* = zip / (body sent + rest) bounds the receive rate \
             from below. Median [min – max] of {} run(s).\n",
            self.socket_buffer_max_bytes
                .map_or("an unknown amount".into(), |b| format!("{:.0} MiB", b as f64 / MIB)),
            self.options.repeats()
        );
        let mut table = Table::new([
            "Zip",
            "Slices",
            "Slice px",
            "Spacing mm",
            "DICOM MiB",
            "Zip MiB",
            "Body sent s",
            "MiB/s sent",
            "Receive MiB/s ≥",
            "To 201 s",
            "End-to-end MiB/s",
            "After body s",
            "load_ct s",
            "Segmentation s",
            "Model s",
            "Rest s",
            "Server slices",
            "Elements",
        ]);
        let median_range =
            |t: &TimeStats| format!("{:.2} [{:.2} – {:.2}]", t.median_s, t.min_s, t.max_s);
        for u in &self.uploads {
            match u {
                Outcome::Measured(u) => {
                    table.row([
                        u.compression.clone(),
                        u.slices.to_string(),
                        format!("{}×{}", u.slice_pixels[0], u.slice_pixels[1]),
                        format!(
                            "{:.2}×{:.2}×{:.2}",
                            u.spacing_mm[0], u.spacing_mm[1], u.spacing_mm[2]
                        ),
                        format!("{:.1}", u.dicom_bytes as f64 / MIB),
                        format!("{:.1}", u.zip_bytes as f64 / MIB),
                        median_range(&u.body_sent),
                        format!("{:.1}", u.transfer_mib_per_s),
                        format!("{:.1}", u.transfer_lower_bound_mib_per_s),
                        median_range(&u.to_201),
                        format!("{:.1}", u.end_to_end_mib_per_s),
                        format!("{:.2}", u.after_body.median_s),
                        format!("{:.2}", u.load_ct_in_process.median_s),
                        format!("{:.2}", u.server_segmentation_s),
                        format!("{:.2}", u.server_model_s),
                        format!("{:.2}", u.server_rest_s),
                        u.server_slice_count.to_string(),
                        u.elements.to_string(),
                    ]);
                }
                Outcome::Failed(e) | Outcome::Skipped(e) => {
                    table.partial_row([one_line(e)]);
                }
            }
        }
        table.write_to(s);
    }

    fn write_overhead(&self, s: &mut String) {
        let _ = writeln!(s, "\n## Service against the CLI, same job\n");
        match &self.overhead {
            Outcome::Measured(o) => {
                let _ = writeln!(
                    s,
                    "`{}`, generated trace (two Lujan breaths, {TRACE_DURATION_S} s at \
                     {TRACE_RATE_HZ} Hz), server defaults at {} mm, {} frames. (a) \
                     `run_breathing` in-process (the CLI's work: load, ingest, solve, write \
                     fields, quick looks, summary); (b) POST the simulation → poll \
                     `GET /v1/jobs/{{id}}` every {POLL_INTERVAL_MS} ms → GET the frame list and \
                     all {} fields ({:.1} MiB). Interleaved rounds, medians [min – max]. The \
                     scan's upload ({:.2} s) is not in (b). Fields byte-identical to the \
                     CLI's: {}.\n",
                    o.ct,
                    o.element_size_mm,
                    o.frames,
                    o.frames,
                    o.field_bytes as f64 / MIB,
                    o.nifti_upload_s,
                    if o.fields_identical_to_cli {
                        "yes"
                    } else {
                        "**no**"
                    }
                );
                let mut table = Table::new([
                    "(a) CLI s",
                    "(b) service s",
                    "of which until done s",
                    "of which fetching s",
                    "b / a",
                    "b − a s",
                    "polls",
                ]);
                let median_range =
                    |t: &TimeStats| format!("{:.3} [{:.3} – {:.3}]", t.median_s, t.min_s, t.max_s);
                table.row([
                    median_range(&o.cli),
                    median_range(&o.service),
                    format!("{:.3}", o.service_until_done.median_s),
                    format!("{:.3}", o.service_fetch.median_s),
                    format!("{:.2}", o.ratio),
                    format!("{:+.3}", o.overhead_s),
                    o.polls_last_round.to_string(),
                ]);
                table.write_to(s);
            }
            Outcome::Failed(e) | Outcome::Skipped(e) => {
                let _ = writeln!(s, "Not measured: {}", one_line(e));
            }
        }
    }

    fn write_load(&self, s: &mut String) {
        let _ = writeln!(s, "\n## Load over loopback\n");
        let _ = writeln!(
            s,
            "{LOAD_CONCURRENCY} concurrent requests for {} s after a {LOAD_WARMUP_S} s \
             warm-up, on a done job of the phantom. The load tool runs in the same process \
             and on the same {} cores as the server. wrk's MiB/s is its Transfer/sec \
             (headers included).\n",
            self.options.load_duration_s(),
            self.cores
        );
        load_table(self.load.iter().chain(&self.wrk)).write_to(s);
    }

    fn write_popi(&self, s: &mut String) {
        let _ = writeln!(s, "\n## Serving at clinical scale: the POPI CT\n");
        let p = match &self.popi {
            Outcome::Measured(p) => p,
            Outcome::Failed(e) => {
                let _ = writeln!(s, "Failed: {}", one_line(e));
                return;
            }
            Outcome::Skipped(e) => {
                let _ = writeln!(s, "Skipped: {}", one_line(e));
                return;
            }
        };
        let [nx, ny, nz] = p.field_dims;
        let _ = writeln!(
            s,
            "The POPI series ({} slices, zip of {:.1} MiB, entries stored) uploaded once \
             ({:.2} s to the 201), then {} jobs of {} phases at {} mm, one after the other. \
             Each field is the lung box, {nx} × {ny} × {nz} voxels ({:.1} M), {:.2} MiB gzipped.\n",
            p.slices,
            p.zip_bytes as f64 / MIB,
            p.upload_to_201_s,
            p.until_done.runs,
            p.frames,
            p.element_size_mm,
            (nx * ny * nz) as f64 / 1e6,
            p.field_bytes as f64 / MIB,
        );
        let ms = |t: &TimeStats| format!("{:.2} s [{:.2} – {:.2}]", t.median_s, t.min_s, t.max_s);
        let mut table = Table::new(["Per job", "median [range]"]);
        table.row(["submit → `done` (20 ms polls)".into(), ms(&p.until_done)]);
        table.row([
            "key solves and frames (`motion_solve`)".into(),
            ms(&p.motion_solve),
        ]);
        table.row([
            format!(
                "writing the {} fields after the solves (`frame_files`)",
                p.frames
            ),
            ms(&p.frame_files),
        ]);
        table.row([
            "**fields written per second after the solves**".into(),
            format!("**{:.1}**", p.fields_written_per_s),
        ]);
        table.row([
            format!(
                "fetching the frame list and the {} fields, one by one",
                p.frames
            ),
            ms(&p.fetch_all),
        ]);
        table.write_to(s);
        let _ = writeln!(s);
        load_table([&p.load, &p.wrk]).write_to(s);
    }

    fn write_queue(&self, s: &mut String) {
        let q = &self.queue;
        let _ = writeln!(s, "\n## The PostgreSQL queue\n");
        if !q.postgres.is_empty() {
            let _ = writeln!(s, "{}.\n", q.postgres);
        }
        let ms = |t: &TimeStats| {
            format!(
                "{:.2} [{:.2} – {:.2}]",
                t.median_s * 1e3,
                t.min_s * 1e3,
                t.max_s * 1e3
            )
        };
        match &q.overhead {
            Outcome::Measured(o) => {
                let _ = writeln!(
                    s,
                    "The queue's own calls per job, from the worker's side, on {} no-op jobs \
                     taken one after the other; median [min – max], ms. Per job (claim + one \
                     heartbeat + completion): **{:.2} ms**; a run adds one heartbeat per \
                     renewal interval (a third of the lease, at most 1 s).\n",
                    o.jobs,
                    o.per_job_s * 1e3
                );
                let mut table = Table::new(["Call", "ms"]);
                for (name, t) in [
                    ("submit (API)", &o.submit),
                    ("claim", &o.claim),
                    ("heartbeat", &o.heartbeat),
                    ("complete", &o.complete),
                ] {
                    table.row([name.to_string(), ms(t)]);
                }
                table.write_to(s);
                let _ = writeln!(
                    s,
                    "\nThe queue alone: no-op jobs claimed, renewed once and completed by \
                     threads at once.\n"
                );
                let mut table = Table::new(["Threads", "Jobs", "s", "Jobs/min"]);
                for r in &o.queue_only_jobs_per_min {
                    table.row([
                        r.threads.to_string(),
                        r.jobs.to_string(),
                        format!("{:.2}", r.wall_s),
                        format!("{:.0}", r.jobs_per_min),
                    ]);
                }
                table.write_to(s);
            }
            Outcome::Failed(e) | Outcome::Skipped(e) => {
                let _ = writeln!(s, "Queue calls not measured: {}", one_line(e));
            }
        }
        match &q.workers {
            Outcome::Measured(rows) => {
                let _ = writeln!(
                    s,
                    "\nShort jobs (the phantom at {} mm, {} phases, no quick looks) submitted \
                     at once to an API server, run by 1, 2 and 4 workers of one simulation \
                     thread each, all in this process on its cores; from the first submission \
                     to the last `done`. Rounds interleave the worker counts; median round.\n",
                    super::queue::SHORT_JOB_ELEMENT_SIZE_MM,
                    super::queue::SHORT_JOB_PHASES
                );
                let mut table = Table::new(["Workers", "Jobs", "s", "Jobs/min", "Rounds jobs/min"]);
                for r in rows {
                    table.row([
                        r.workers.to_string(),
                        r.jobs.to_string(),
                        format!(
                            "{:.1} [{:.1} – {:.1}]",
                            r.wall.median_s, r.wall.min_s, r.wall.max_s
                        ),
                        format!("{:.1}", r.jobs_per_min),
                        r.rounds_jobs_per_min
                            .iter()
                            .map(|j| format!("{j:.1}"))
                            .collect::<Vec<_>>()
                            .join(", "),
                    ]);
                }
                table.write_to(s);
            }
            Outcome::Failed(e) | Outcome::Skipped(e) => {
                let _ = writeln!(s, "\nWorkers not measured: {}", one_line(e));
            }
        }
    }
}

/// One row per load run (failed and skipped ones say why).
fn load_table<'a>(outcomes: impl IntoIterator<Item = &'a Outcome<LoadResult>>) -> Table {
    let mut table = Table::new([
        "Endpoint",
        "Tool",
        "Requests",
        "Errors",
        "Req/s",
        "p50 ms",
        "p99 ms",
        "max ms",
        "MiB/s",
        "Body bytes",
    ]);
    for o in outcomes {
        match o {
            Outcome::Measured(l) => {
                table.row([
                    format!("`{}`", l.endpoint),
                    l.tool.clone(),
                    l.requests.to_string(),
                    l.errors.to_string(),
                    format!("{:.0}", l.requests_per_s),
                    format!("{:.2}", l.latency_p50_ms),
                    format!("{:.2}", l.latency_p99_ms),
                    format!("{:.1}", l.latency_max_ms),
                    format!("{:.1}", l.mib_per_s),
                    if l.body_bytes > 0 {
                        l.body_bytes.to_string()
                    } else {
                        "–".into()
                    },
                ]);
            }
            Outcome::Failed(e) | Outcome::Skipped(e) => {
                table.partial_row([one_line(e)]);
            }
        }
    }
    table
}
