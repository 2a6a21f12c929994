"""Run every benchmark in turn; each prints its figures and rewrites its docs section."""

import importlib

BENCHMARKS = (
    "bench.bench_fit",
    "bench.bench_stream_fit",
    "bench.bench_match",
    "bench.bench_coco_ap",
    "bench.bench_box_regions",
    "bench.bench_detectors",
    "bench.bench_service",
    "bench.bench_health",
    "bench.bench_steady",
)

if __name__ == "__main__":
    for name in BENCHMARKS:
        print(f"== {name}", flush=True)
        importlib.import_module(name).main([])
