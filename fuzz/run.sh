#!/usr/bin/env bash
# Runs each fuzz target for a set time under memory limits and prints one table row per
# target: executions, crashes, timeouts and out-of-memory findings, peak RSS.
#
#   fuzz/run.sh <seconds> [target ...]      (all targets when none is named)
#
# Environment: FUZZ_JOBS targets at a time (default 1; the machine is shared), FUZZ_NICE
# (default 15), FUZZ_SANITIZER (address, the default, or none), RSS_LIMIT_MB and
# MALLOC_LIMIT_MB (default 2048 each), FUZZ_TIMEOUT_S seconds one input may take (default 10).
#
# libFuzzer stops at its first finding; the run is then resumed from the grown corpus until
# the time is spent, so one target's time counts every round. Findings land in
# fuzz/artifacts/<target>/ (crash-*, timeout-*, oom-*); logs in fuzz/runs/<target>.log and the
# table in fuzz/runs/summary.md. Build needs cargo-fuzz (`cargo install cargo-fuzz`); on a
# stable toolchain RUSTC_BOOTSTRAP=1 lets it pass the -Z sanitizer flags libFuzzer needs.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
cd "$here"
seconds="${1:?usage: fuzz/run.sh <seconds> [target ...]}"
shift
all_targets=(dicom_series nifti nrrd metaimage trace_csv trace_json zip)
targets=("$@")
[[ ${#targets[@]} -gt 0 ]] || targets=("${all_targets[@]}")
jobs="${FUZZ_JOBS:-1}"
niceness="${FUZZ_NICE:-15}"
sanitizer="${FUZZ_SANITIZER:-address}"
rss_mb="${RSS_LIMIT_MB:-2048}"
malloc_mb="${MALLOC_LIMIT_MB:-2048}"
timeout_s="${FUZZ_TIMEOUT_S:-10}"
triple="$(rustc -vV | sed -n 's/^host: //p')"
bin_dir="$here/target/$triple/release"

[[ -d corpus ]] || ./seed.sh
mkdir -p runs
# -a keeps debug assertions (integer overflow checks) in the fuzzed build; with no target
# named, `cargo fuzz build` builds them all.
RUSTC_BOOTSTRAP=1 nice -n "$niceness" cargo fuzz build -a -s "$sanitizer" >runs/build.log 2>&1 ||
    { tail -n 30 runs/build.log; exit 1; }

# One target for `seconds`: rounds of libFuzzer until the time is spent; writes
# runs/<target>.row (executions, crashes, timeouts, ooms, peak RSS MB).
fuzz_one() {
    local t="$1" log="runs/$1.log" deadline=$((SECONDS + seconds)) execs=0 peak_kb=0 rounds=0
    mkdir -p "corpus/$t" "artifacts/$t"
    : >"$log"
    touch "runs/$t.start"
    while ((SECONDS < deadline && rounds < 50)); do
        rounds=$((rounds + 1))
        local left=$((deadline - SECONDS))
        ((left > 0)) || break
        local round="runs/$t.round"
        nice -n "$niceness" /usr/bin/time -f 'maxrss_kb %M' -o "runs/$t.time" \
            "$bin_dir/$t" "corpus/$t" -max_total_time="$left" -rss_limit_mb="$rss_mb" \
            -malloc_limit_mb="$malloc_mb" -timeout="$timeout_s" -print_final_stats=1 \
            -artifact_prefix="artifacts/$t/" >"$round" 2>&1 || true
        cat "$round" "runs/$t.time" >>"$log"
        # Executions: the final stats when libFuzzer printed them, else (it stopped on an
        # out-of-memory or a timeout) the last status line's count.
        local e k
        e="$(grep -o 'stat::number_of_executed_units: [0-9]*' "$round" | grep -o '[0-9]*$' || true)"
        [[ -n "$e" ]] || e="$(grep -o '^#[0-9]*' "$round" | tail -n 1 | tr -d '#' || true)"
        execs=$((execs + ${e:-0}))
        k="$(grep -o 'maxrss_kb [0-9]*' "runs/$t.time" | grep -o '[0-9]*$' || echo 0)"
        ((k > peak_kb)) && peak_kb=$k
        # A clean end of the time leaves no new artifact: nothing to resume for.
        grep -q 'Done [0-9]* runs in' "$round" && break
    done
    local crashes timeouts ooms
    crashes="$(find "artifacts/$t" -name 'crash-*' -newer "runs/$t.start" | wc -l)"
    timeouts="$(find "artifacts/$t" -name 'timeout-*' -newer "runs/$t.start" | wc -l)"
    ooms="$(find "artifacts/$t" -name 'oom-*' -newer "runs/$t.start" | wc -l)"
    echo "$t $seconds $execs $crashes $timeouts $ooms $((peak_kb / 1024)) $rounds" >"runs/$t.row"
}

running=0
for t in "${targets[@]}"; do
    fuzz_one "$t" &
    running=$((running + 1))
    if ((running >= jobs)); then
        wait -n || true
        running=$((running - 1))
    fi
done
wait

{
    echo "| target | seconds | executions | crashes | timeouts | OOMs | peak RSS (MB) | rounds |"
    echo "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"
    for t in "${targets[@]}"; do
        read -r name secs execs crashes timeouts ooms rss rounds <"runs/$t.row"
        echo "| $name | $secs | $execs | $crashes | $timeouts | $ooms | $rss | $rounds |"
    done
} | tee runs/summary.md
echo "(sanitizer $sanitizer, -rss_limit_mb=$rss_mb -malloc_limit_mb=$malloc_mb -timeout=$timeout_s; findings in fuzz/artifacts/)"
