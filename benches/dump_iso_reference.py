"""Write the reference of the campaign benchmark's ISO standard cycle, one value per line (m).

The Rust profile example reads it: ``cargo run --release --no-default-features --example
profile_loop -- iso FILE`` (work per phase of one campaign trial; see the example's header).

    python benches/dump_iso_reference.py [FILE]   (default /tmp/iso_ref.txt)
"""

from __future__ import annotations

import sys

import numpy as np
from campaign_speed import setup


def main() -> None:
    path = sys.argv[1] if len(sys.argv) > 1 else "/tmp/iso_ref.txt"
    _, cycle, moves = setup(10.0, 0.2)
    np.savetxt(path, cycle.reference_m, fmt="%.17g")
    print(f"{path}: {len(cycle.reference_m)} samples, {moves} moves")


if __name__ == "__main__":
    main()
