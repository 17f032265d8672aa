//! Listing what is stored: scans and jobs, newest first, a page at a time.
//!
//! Pages are cut by a cursor, not an offset: the cursor names the last item of the page
//! (its creation time and id), so a scan uploaded or a job deleted between two requests
//! neither repeats nor skips an item of the pages that follow. The cursor is opaque to
//! clients (hex of `created_at` and the id); the `next` link carries it with the filters.

use axum::extract::{Query, State};
use axum::Json;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::{blocking, store_error, JobStatus, ScanView, SharedState};
use crate::service::ids::ScanId;
use crate::service::problem::{ApiError, ApiResult, Problem};
use crate::service::store::JobState;

/// Items per page unless the client asks otherwise.
pub const DEFAULT_PAGE_SIZE: usize = 50;
/// Most items a page holds.
pub const MAX_PAGE_SIZE: usize = 500;

/// The query of a listing; every field is text so that a bad value gets a problem naming it.
#[derive(Debug, Default, Deserialize)]
pub struct ListQuery {
    /// Items per page (1 to 500).
    pub limit: Option<String>,
    /// The `next_cursor` of the previous page.
    pub after: Option<String>,
    /// Jobs only: keep the jobs in this state.
    pub state: Option<String>,
    /// Jobs only: keep the jobs of this scan.
    pub scan_id: Option<String>,
}

/// One page of stored scans.
#[derive(Debug, Serialize, ToSchema)]
pub struct ScanPage {
    /// The scans, newest first.
    pub items: Vec<ScanView>,
    /// Scans stored in all.
    pub total: usize,
    /// The cursor of the next page; absent on the last one.
    pub next_cursor: Option<String>,
    /// The next page's URL; absent on the last one.
    pub next: Option<String>,
}

/// One page of jobs.
#[derive(Debug, Serialize, ToSchema)]
pub struct JobPage {
    /// The jobs, newest first.
    pub items: Vec<JobStatus>,
    /// Jobs matching the filters in all.
    pub total: usize,
    /// The cursor of the next page; absent on the last one.
    pub next_cursor: Option<String>,
    /// The next page's URL; absent on the last one.
    pub next: Option<String>,
}

/// Where a page starts and how long it is, checked.
#[derive(Debug, Clone, PartialEq)]
struct PageRequest {
    limit: usize,
    /// The key of the item the previous page ended with.
    after: Option<SortKey>,
}

/// What items are ordered by: creation time (RFC 3339, UTC, so text order is time order),
/// then id, both descending.
type SortKey = (String, String);

impl PageRequest {
    fn of(query: &ListQuery) -> ApiResult<Self> {
        let limit = match &query.limit {
            None => DEFAULT_PAGE_SIZE,
            Some(text) => match text.trim().parse::<usize>() {
                Ok(n) if (1..=MAX_PAGE_SIZE).contains(&n) => n,
                _ => {
                    return Err(ApiError::bad_request(
                        "invalid-limit",
                        format!("query parameter limit: {text:?} is not a whole number from 1 to {MAX_PAGE_SIZE}"),
                    ))
                }
            },
        };
        let after = query.after.as_deref().map(decode_cursor).transpose()?;
        Ok(PageRequest { limit, after })
    }
}

/// The cursor naming the item with `key`.
fn encode_cursor(key: &SortKey) -> String {
    let text = format!("{}\n{}", key.0, key.1);
    text.bytes().map(|b| format!("{b:02x}")).collect()
}

/// The key a cursor names, or 400.
fn decode_cursor(cursor: &str) -> ApiResult<SortKey> {
    let bad = || {
        ApiError::bad_request(
            "invalid-cursor",
            format!(
                "query parameter after: {:?} is not a cursor this server gave",
                cursor.chars().take(80).collect::<String>()
            ),
        )
    };
    if !cursor.len().is_multiple_of(2) || cursor.len() > 512 {
        return Err(bad());
    }
    let bytes = (0..cursor.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(cursor.get(i..i + 2).ok_or_else(bad)?, 16).map_err(|_| bad()))
        .collect::<ApiResult<Vec<u8>>>()?;
    let text = String::from_utf8(bytes).map_err(|_| bad())?;
    let (time, id) = text.split_once('\n').ok_or_else(bad)?;
    Ok((time.to_string(), id.to_string()))
}

/// The page of `items` (any order) that `page` asks for, the total and the next cursor.
fn cut_page<T>(
    mut items: Vec<T>,
    key: impl Fn(&T) -> SortKey,
    page: &PageRequest,
) -> (Vec<T>, usize, Option<String>) {
    let total = items.len();
    items.sort_by_cached_key(|item| std::cmp::Reverse(key(item)));
    let start = match &page.after {
        None => 0,
        // Newest first: the page goes on with the first item older than the cursor's.
        Some(after) => items.partition_point(|item| key(item) >= *after),
    };
    let rest = items.len() - start;
    let kept: Vec<T> = items.into_iter().skip(start).take(page.limit).collect();
    let next = (rest > page.limit)
        .then(|| kept.last().map(|last| encode_cursor(&key(last))))
        .flatten();
    (kept, total, next)
}

/// The next page's URL: `path` with the filters and the cursor.
fn next_link(path: &str, filters: &[(&str, String)], limit: usize, cursor: &str) -> String {
    let mut link = format!("{path}?limit={limit}");
    for (name, value) in filters {
        // Filter values are ids and state names: hex digits and letters, nothing to escape.
        link.push_str(&format!("&{name}={value}"));
    }
    link.push_str(&format!("&after={cursor}"));
    link
}

/// List stored scans, newest first.
#[utoipa::path(
    get, path = "/v1/scans", tag = "scans",
    params(
        ("limit" = Option<u32>, Query, description = "Scans per page, 1 to 500 (default 50)"),
        ("after" = Option<String>, Query, description = "The previous page's `next_cursor`"),
    ),
    responses(
        (status = 200, description = "A page of scans, newest first", body = ScanPage),
        (status = 400, description = "A limit out of range or a cursor this server did not give", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn list_scans(
    State(state): State<SharedState>,
    Query(query): Query<ListQuery>,
) -> ApiResult<Json<ScanPage>> {
    let page = PageRequest::of(&query)?;
    blocking(move || {
        let (scans, problems) = state.records.list_scans().map_err(store_error)?;
        for problem in problems {
            tracing::warn!(%problem, "scan listing skipped a directory");
        }
        let records = scans.into_iter().map(|(record, _bytes)| record).collect();
        let (items, total, next_cursor) = cut_page(
            records,
            |r| (r.created_at.clone(), r.scan_id.to_string()),
            &page,
        );
        Ok(Json(ScanPage {
            next: next_cursor
                .as_deref()
                .map(|c| next_link("/v1/scans", &[], page.limit, c)),
            next_cursor,
            total,
            items: items.into_iter().map(ScanView::from).collect(),
        }))
    })
    .await
}

/// List jobs, newest first, optionally of one scan or in one state.
#[utoipa::path(
    get, path = "/v1/jobs", tag = "jobs",
    params(
        ("limit" = Option<u32>, Query, description = "Jobs per page, 1 to 500 (default 50)"),
        ("after" = Option<String>, Query, description = "The previous page's `next_cursor`"),
        ("state" = Option<String>, Query, description = "Only jobs in this state: queued, running, cancelling, done, failed or cancelled"),
        ("scan_id" = Option<String>, Query, description = "Only the jobs of this scan"),
    ),
    responses(
        (status = 200, description = "A page of jobs, newest first", body = JobPage),
        (status = 400, description = "A limit out of range, an unknown state, a malformed scan id or a cursor this server did not give", body = Problem, content_type = "application/problem+json"),
    ),
    security(("bearer" = []))
)]
pub async fn list_jobs(
    State(state): State<SharedState>,
    Query(query): Query<ListQuery>,
) -> ApiResult<Json<JobPage>> {
    let page = PageRequest::of(&query)?;
    let wanted_state = query
        .state
        .as_deref()
        .map(|text| {
            JobState::ALL
                .into_iter()
                .find(|s| s.name() == text)
                .ok_or_else(|| {
                    ApiError::bad_request(
                        "invalid-state",
                        format!("query parameter state: {text:?} is not one of queued, running, cancelling, done, failed, cancelled"),
                    )
                })
        })
        .transpose()?;
    let wanted_scan = query
        .scan_id
        .as_deref()
        .map(|text| {
            ScanId::parse(text).ok_or_else(|| {
                ApiError::bad_request(
                    "invalid-scan-id",
                    format!("query parameter scan_id: {text:?} is not a scan id (32 hex digits)"),
                )
            })
        })
        .transpose()?;
    let records = state
        .jobs
        .records()
        .map_err(store_error)?
        .into_iter()
        .filter(|r| wanted_state.is_none_or(|s| r.state == s))
        .filter(|r| wanted_scan.is_none_or(|id| r.scan_id == id))
        .collect();
    let (items, total, next_cursor) = cut_page(
        records,
        |r| (r.created_at.clone(), r.job_id.to_string()),
        &page,
    );
    let mut filters = Vec::new();
    if let Some(s) = wanted_state {
        filters.push(("state", s.name().to_string()));
    }
    if let Some(id) = wanted_scan {
        filters.push(("scan_id", id.to_string()));
    }
    Ok(Json(JobPage {
        next: next_cursor
            .as_deref()
            .map(|c| next_link("/v1/jobs", &filters, page.limit, c)),
        next_cursor,
        total,
        items: items.into_iter().map(JobStatus::from).collect(),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn page(limit: usize, after: Option<SortKey>) -> PageRequest {
        PageRequest { limit, after }
    }

    #[test]
    fn pages_walk_every_item_once_newest_first_even_with_equal_times() {
        // Five items, two created in the same second (ids break the tie).
        let items: Vec<SortKey> = vec![
            ("2026-12-01T10:00:00Z".into(), "b".into()),
            ("2026-12-01T09:00:00Z".into(), "a".into()),
            ("2026-12-01T10:00:00Z".into(), "a".into()),
            ("2026-12-01T11:00:00Z".into(), "c".into()),
            ("2026-12-01T08:00:00Z".into(), "d".into()),
        ];
        let mut seen = Vec::new();
        let mut after = None;
        loop {
            let (kept, total, next) = cut_page(items.clone(), |k| k.clone(), &page(2, after));
            assert_eq!(total, 5);
            seen.extend(kept);
            match next {
                Some(cursor) => after = Some(decode_cursor(&cursor).unwrap()),
                None => break,
            }
        }
        let ids: Vec<&str> = seen.iter().map(|k| k.1.as_str()).collect();
        assert_eq!(ids, ["c", "b", "a", "a", "d"]);
        assert_eq!(seen[2].0, "2026-12-01T10:00:00Z");
    }

    #[test]
    fn an_item_removed_between_pages_skips_nothing_else() {
        let items: Vec<SortKey> = (0..6)
            .map(|i| (format!("2026-12-01T10:00:0{i}Z"), format!("{i}")))
            .collect();
        let (first, _, next) = cut_page(items.clone(), |k| k.clone(), &page(3, None));
        assert_eq!(
            first.iter().map(|k| &k.1[..]).collect::<Vec<_>>(),
            ["5", "4", "3"]
        );
        // Item 3 (the cursor's own) and item 2 are deleted before the next request.
        let left: Vec<SortKey> = items
            .into_iter()
            .filter(|k| k.1 != "3" && k.1 != "2")
            .collect();
        let after = decode_cursor(&next.unwrap()).unwrap();
        let (second, _, next) = cut_page(left, |k| k.clone(), &page(3, Some(after)));
        assert_eq!(
            second.iter().map(|k| &k.1[..]).collect::<Vec<_>>(),
            ["1", "0"]
        );
        assert!(next.is_none());
    }

    #[test]
    fn limits_and_cursors_from_elsewhere_are_refused() {
        for bad in ["0", "501", "-3", "ten"] {
            let q = ListQuery {
                limit: Some(bad.into()),
                ..ListQuery::default()
            };
            assert!(PageRequest::of(&q).is_err(), "{bad}");
        }
        for bad in ["zz", "abc", "61", &"6".repeat(600)] {
            assert!(decode_cursor(bad).is_err(), "{bad}");
        }
        let key = ("2026-12-01T10:00:00Z".to_string(), "ab12".to_string());
        assert_eq!(decode_cursor(&encode_cursor(&key)).unwrap(), key);
    }
}
