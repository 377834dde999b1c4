"""Accuracy against cost: the knobs of vantage's viewport index, each measured against the exact answer.

Run from the repository root (seeded; rewrites the report and its plots)::

    python -m benchmarks.tradeoffs                                       # ~1M items per scene (minutes)
    python -m benchmarks.tradeoffs --scale 0.05 --out /tmp/tradeoffs.md  # a quick look (under a minute)
    python -m benchmarks.tradeoffs --trades aggregates --update          # one trade, into the report

Six trades, each a table and a plot (written next to the report as tradeoffs-<trade>.png):

  exact     tree.query(rect, exact=False): the touched leaves' items untested, a superset
  lod       tree.query(rect, min_size=min_px/scale): items under min_px on screen left out
  float32   QuadTree(coords="float32"): boxes in half the memory, rounded outward (false hits)
  shape     leaf_size, max_depth and x_order: build time, memory, query time
  overscan  the panning simulator's margin: requests/s, bytes/s and blank screen
  aggregates  zoomed out: every item, drop-only LOD, or the overview's aggregates against the
            exact picture, entries per screen and server time, from page level to the whole
            scene; Overview.build against QuadTree.bulk_load (and docs/zoom-out.png)

The exact answer is brute force over the float64 boxes with closed intervals (touching counts).
Query times are medians of calls interleaved step by step in a seeded shuffled order, so a
noisy neighbour slows every variant alike and the ratios hold.
"""

# The docstring above is also the command line's --help. The package, a module a piece:
#   __main__         the command line: parse the options, run the trades asked for, write the report
#   scene            the three scenes (boxes, kinds, panning path, default tree)
#   measure          brute-force truth, comparing answers, interleaved timing, timed builds
#   render           viewports as pictures of kinds (trades 2 and 6)
#   report           Markdown tables, number formats, plotting, the report's header and --update's splice
#   exact, lod, float32, shape, overscan, aggregates
#                    one trade each: its rows, its measurement, its section, its plot, its advice
#   recommendations  the closing section, from every trade's advice
