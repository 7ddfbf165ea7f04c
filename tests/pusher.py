"""A hostile Rerun client for tests: pushes ``MB`` megabytes into a gRPC server.

    python tests/pusher.py URL KIND MB      # KIND: temporal, static or blueprint

Blueprints are the worst case: Rerun's server keeps them outside its memory limit.
"""

from __future__ import annotations

import sys
import time

import numpy as np
import rerun as rr
import rerun.blueprint as rrb


def main() -> int:
    url, kind, mb = sys.argv[1], sys.argv[2], int(sys.argv[3])
    rec = rr.RecordingStream("ballbar", recording_id="injected")
    rec.set_sinks(rr.GrpcSink(url))
    rng = np.random.default_rng(0)
    for i in range(mb):
        if kind == "blueprint":
            rec.send_blueprint(rrb.Blueprint(rrb.TextDocumentView(origin="/" + rng.bytes(1 << 19).hex())))
        else:
            blob = rng.integers(0, 255, size=(1024, 1024), dtype=np.uint8)
            if kind == "temporal":
                rec.set_time("time", timestamp=time.time())
            rec.log("findings" if kind == "temporal" else f"junk/{i}", rr.Image(blob), static=kind == "static")
    rec.flush(timeout_sec=60)
    return 0


if __name__ == "__main__":
    sys.exit(main())
