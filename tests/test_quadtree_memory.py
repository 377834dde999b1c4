"""What a tree's build holds above its input: the peak an import reaches at 1e7 items and beyond.
Measured in a process of its own, its private memory sampled from ``/proc`` while it builds;
glibc is told to map every large block on its own, so a freed array goes back at once and
the samples see what is held, not what the heap kept."""

import os
import subprocess
import sys
import textwrap

ITEMS = 1_000_000

CHILD = textwrap.dedent(
    """
    import os, sys, threading, time
    import numpy as np
    from benchmarks.scale import private_bytes
    from spatial import QuadTree

    n = int(sys.argv[1])
    rng = np.random.default_rng(7)
    xy = rng.uniform(0, 1e6, (n, 2))
    boxes = np.hstack([xy, xy + rng.uniform(1, 50, (n, 2))])
    del xy
    QuadTree.bulk_load(boxes[:1000])  # compiled (or loaded from the cache) before the samples
    base, peak, done = private_bytes(os.getpid()), [0], threading.Event()

    def sample():
        while not done.is_set():
            peak[0] = max(peak[0], private_bytes(os.getpid()))
            time.sleep(0.0005)

    sampler = threading.Thread(target=sample)
    sampler.start()
    tree = QuadTree.bulk_load(boxes)
    done.set()
    sampler.join()
    assert len(tree) == n
    print((peak[0] - base) / n)
    """
)


def test_a_trees_build_holds_about_fifty_bytes_an_item_above_its_boxes():
    """The keys (8 bytes an item), the order (8), the boxes in the tree's order (32) and the
    nodes' ranges, then their records (~14): ~50 bytes an item at the peak. It was ~80: the
    take into the tree's order was buffered into a second copy of the boxes, and the keys
    were held while the node records were made (and copied, to align them)."""
    env = dict(os.environ, MALLOC_MMAP_THRESHOLD_="65536")
    done = subprocess.run(
        [sys.executable, "-c", CHILD, str(ITEMS)], capture_output=True, text=True, env=env, timeout=300
    )
    assert done.returncode == 0, done.stderr
    per_item = float(done.stdout)
    assert 32 < per_item < 64, per_item  # above 32: the samples saw the build at all
