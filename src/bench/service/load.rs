//! Requests per second over loopback: the built-in load tool and, when on PATH, `wrk`.

use std::sync::Arc;
use std::time::{Duration, Instant};

use super::{http_error, Bench, LoadResult, LOAD_CONCURRENCY, LOAD_WARMUP_S, MIB, WRK_THREADS};
use crate::bench::Outcome;
use crate::Result;

impl Bench {
    /// C tasks hitting `url` for `duration_s` after a short warm-up.
    pub(super) fn load(&self, route: &str, url: &str, duration_s: f64) -> Result<LoadResult> {
        self.runtime.block_on(async {
            let url: Arc<str> = Arc::from(url);
            let warm_end = Instant::now() + Duration::from_secs_f64(LOAD_WARMUP_S);
            self.load_tasks(&url, warm_end, 0).await?;
            let start = Instant::now();
            let end = start + Duration::from_secs_f64(duration_s);
            // Room for a few thousand requests per task, so the loop does not reallocate.
            let tallies = self.load_tasks(&url, end, 1 << 15).await?;
            let elapsed_s = start.elapsed().as_secs_f64();
            let mut latencies: Vec<f64> =
                Vec::with_capacity(tallies.iter().map(|t| t.latencies_s.len()).sum::<usize>());
            let (mut errors, mut bytes, mut body_bytes) = (0u64, 0u64, 0u64);
            for t in &tallies {
                latencies.extend_from_slice(&t.latencies_s);
                errors += t.errors;
                bytes += t.bytes;
                body_bytes = body_bytes.max(t.body_bytes);
            }
            latencies.sort_by(f64::total_cmp);
            let requests = latencies.len() as u64;
            Ok(LoadResult {
                endpoint: route.into(),
                tool: "built-in (tokio + reqwest, one keep-alive client)".into(),
                concurrency: LOAD_CONCURRENCY,
                duration_s: elapsed_s,
                requests,
                errors,
                requests_per_s: requests as f64 / elapsed_s,
                latency_p50_ms: percentile(&latencies, 0.50) * 1e3,
                latency_p99_ms: percentile(&latencies, 0.99) * 1e3,
                latency_max_ms: latencies.last().copied().unwrap_or(f64::NAN) * 1e3,
                mib_per_s: bytes as f64 / MIB / elapsed_s,
                body_bytes,
            })
        })
    }

    /// Runs the load tasks until `end` and collects their tallies.
    async fn load_tasks(
        &self,
        url: &Arc<str>,
        end: Instant,
        capacity: usize,
    ) -> Result<Vec<Tally>> {
        let handles: Vec<_> = (0..LOAD_CONCURRENCY)
            .map(|_| tokio::spawn(load_task(self.client.clone(), url.clone(), end, capacity)))
            .collect();
        let mut tallies = Vec::with_capacity(handles.len());
        for h in handles {
            tallies.push(h.await.map_err(|e| http_error("load task", e))?);
        }
        Ok(tallies)
    }
}

/// What one load task saw.
struct Tally {
    latencies_s: Vec<f64>,
    errors: u64,
    bytes: u64,
    body_bytes: u64,
}

/// Requests `url` back to back until `end`, reading every body to its end without keeping it.
async fn load_task(client: reqwest::Client, url: Arc<str>, end: Instant, capacity: usize) -> Tally {
    let mut tally = Tally {
        latencies_s: Vec::with_capacity(capacity),
        errors: 0,
        bytes: 0,
        body_bytes: 0,
    };
    while Instant::now() < end {
        let t = Instant::now();
        let mut response = match client.get(&*url).send().await {
            Ok(r) => r,
            Err(_) => {
                tally.errors += 1;
                continue;
            }
        };
        let ok = response.status().is_success();
        let mut body = 0u64;
        let mut broken = false;
        loop {
            match response.chunk().await {
                Ok(Some(c)) => body += c.len() as u64,
                Ok(None) => break,
                Err(_) => {
                    broken = true;
                    break;
                }
            }
        }
        if ok && !broken {
            tally.latencies_s.push(t.elapsed().as_secs_f64());
            tally.bytes += body;
            tally.body_bytes = body;
        } else {
            tally.errors += 1;
        }
    }
    tally
}

/// Nearest-rank percentile `p` (0–1) of sorted `values`; NaN when empty.
fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let rank = (p * sorted.len() as f64).ceil() as usize;
    sorted[rank.clamp(1, sorted.len()) - 1]
}

/// Runs `wrk` on `url` when it is on PATH.
pub(super) fn wrk_load(route: &str, url: &str, duration_s: f64) -> Outcome<LoadResult> {
    let seconds = duration_s.ceil().max(1.0) as u64;
    let output = std::process::Command::new("wrk")
        .arg(format!("-t{WRK_THREADS}"))
        .arg(format!("-c{LOAD_CONCURRENCY}"))
        .arg(format!("-d{seconds}s"))
        .arg("--latency")
        .arg(url)
        .output();
    match output {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            Outcome::Skipped("wrk is not on PATH".into())
        }
        Err(e) => Outcome::Failed(format!("wrk: {e}")),
        Ok(o) if !o.status.success() => Outcome::Failed(format!(
            "wrk exited with {}: {}",
            o.status,
            String::from_utf8_lossy(&o.stderr).trim()
        )),
        Ok(o) => match parse_wrk(&String::from_utf8_lossy(&o.stdout), route, seconds as f64) {
            Some(r) => Outcome::Measured(r),
            None => Outcome::Failed(format!(
                "wrk output not understood: {}",
                String::from_utf8_lossy(&o.stdout)
            )),
        },
    }
}

/// A wrk duration (`850.00us`, `1.20ms`, `2.00s`, `1.00m`) in seconds.
fn wrk_seconds(text: &str) -> Option<f64> {
    let split = text.find(|c: char| c.is_ascii_alphabetic())?;
    let (number, unit) = text.split_at(split);
    let v: f64 = number.parse().ok()?;
    Some(match unit {
        "us" => v * 1e-6,
        "ms" => v * 1e-3,
        "s" => v,
        "m" => v * 60.0,
        "h" => v * 3600.0,
        _ => return None,
    })
}

/// A wrk size (`1.50MB`, `12.3KB`, `800B`; binary multiples) in bytes.
fn wrk_bytes(text: &str) -> Option<f64> {
    let split = text.find(|c: char| c.is_ascii_alphabetic())?;
    let (number, unit) = text.split_at(split);
    let v: f64 = number.parse().ok()?;
    let scale = match unit {
        "B" => 1.0,
        "KB" => 1024.0,
        "MB" => MIB,
        "GB" => MIB * 1024.0,
        "TB" => MIB * MIB,
        _ => return None,
    };
    Some(v * scale)
}

/// Reads wrk's `--latency` report.
fn parse_wrk(out: &str, route: &str, duration_s: f64) -> Option<LoadResult> {
    let mut p50 = None;
    let mut p99 = None;
    let mut max = f64::NAN;
    let mut rps = None;
    let mut transfer = None;
    let mut requests = None;
    let mut errors = 0u64;
    let mut elapsed_s = duration_s;
    for line in out.lines() {
        let fields: Vec<&str> = line.split_whitespace().collect();
        match fields.as_slice() {
            ["50%", v] => p50 = wrk_seconds(v),
            ["99%", v] => p99 = wrk_seconds(v),
            ["Latency", _avg, _stdev, m, ..] => max = wrk_seconds(m).unwrap_or(f64::NAN),
            ["Requests/sec:", v] => rps = v.parse::<f64>().ok(),
            ["Transfer/sec:", v] => transfer = wrk_bytes(v),
            [n, "requests", "in", t, ..] => {
                requests = n.parse::<u64>().ok();
                if let Some(s) = wrk_seconds(t.trim_end_matches(',')) {
                    elapsed_s = s;
                }
            }
            ["Non-2xx", "or", "3xx", "responses:", n] => errors += n.parse::<u64>().unwrap_or(0),
            ["Socket", "errors:", rest @ ..] => {
                errors += rest
                    .iter()
                    .filter_map(|x| x.trim_end_matches(',').parse::<u64>().ok())
                    .sum::<u64>()
            }
            _ => {}
        }
    }
    let requests = requests?;
    Some(LoadResult {
        endpoint: route.into(),
        tool: format!("wrk -t{WRK_THREADS} -c{LOAD_CONCURRENCY}"),
        concurrency: LOAD_CONCURRENCY,
        duration_s: elapsed_s,
        requests: requests.saturating_sub(errors),
        errors,
        requests_per_s: rps?,
        latency_p50_ms: p50? * 1e3,
        latency_p99_ms: p99? * 1e3,
        latency_max_ms: max * 1e3,
        mib_per_s: transfer? / MIB,
        body_bytes: 0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_use_the_nearest_rank() {
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&v, 0.5), 50.0);
        assert_eq!(percentile(&v, 0.99), 99.0);
        assert_eq!(percentile(&[3.0], 0.99), 3.0);
        assert!(percentile(&[], 0.5).is_nan());
    }

    #[test]
    fn wrk_report_is_read() {
        let out = "Running 2s test @ http://127.0.0.1:1/v1/jobs/x\n  2 threads and 16 connections\n  Thread Stats   Avg      Stdev     Max   +/- Stdev\n    Latency     1.50ms  300.00us  12.00ms   90.00%\n    Req/Sec     5.00k   100.00     6.00k    70.00%\n  Latency Distribution\n     50%    1.40ms\n     75%    1.60ms\n     90%    1.90ms\n     99%    3.00ms\n  20000 requests in 2.00s, 30.00MB read\n  Non-2xx or 3xx responses: 4\nRequests/sec:  10000.00\nTransfer/sec:     15.00MB\n";
        let r = parse_wrk(out, "GET /v1/jobs/{id}", 2.0).unwrap();
        assert_eq!(r.requests, 19_996);
        assert_eq!(r.errors, 4);
        assert!((r.latency_p50_ms - 1.4).abs() < 1e-9);
        assert!((r.latency_p99_ms - 3.0).abs() < 1e-9);
        assert!((r.latency_max_ms - 12.0).abs() < 1e-9);
        assert!((r.mib_per_s - 15.0).abs() < 1e-9);
        assert!((r.requests_per_s - 10_000.0).abs() < 1e-9);
        assert!(parse_wrk("garbage", "x", 1.0).is_none());
        assert!((wrk_seconds("850.00us").unwrap() - 850e-6).abs() < 1e-15);
    }
}
