#!/usr/bin/env python3
"""Compare two renderings pixel by pixel: depth (PFM) and primitive ids (raw u32).

    scripts/compare_images.py A.pfm A.u32 B.pfm B.u32 [--json] [--tolerance 1e-4]
                              [--min-primid-agreement 99.9] [--max-depth-rel-err 1e-4]

A is the reference (Embree in scripts/bench-kernel), B the renderer under test.
The formats are those of DESIGN.md "Conventions" (and of embree-bench's README):

* depth: grey PFM, header "Pf\\n<W> <H>\\n<scale>\\n" (negative scale = little
  endian), W*H float32 with rows from bottom to top, +inf on a miss;
* primitive ids: W*H raw little-endian uint32, rows from top to bottom,
  0xFFFFFFFF on a miss.

Prints the agreement figures as text, and with --json also one JSON object as
the last line.  The relative depth error of a pixel where both hit is
|tA - tB| / tA.  With --min-primid-agreement and/or --max-depth-rel-err it exits
with status 1 when a figure is worse than the bound (the depth bound applies to
the pixels where both hit the same primitive).

Standard library only.
"""

import argparse
import array
import json
import math
import sys

MISS = 0xFFFFFFFF


class FormatError(Exception):
    pass


def read_pfm(path):
    """Returns (width, height, values) with values in top-to-bottom row order."""
    with open(path, "rb") as f:
        data = f.read()
    # The header is four whitespace-separated tokens (magic, width, height,
    # scale), the last followed by exactly one whitespace byte ("\n" here).
    tokens, pos = [], 0
    while len(tokens) < 4:
        while pos < len(data) and data[pos : pos + 1].isspace():
            pos += 1
        start = pos
        while pos < len(data) and not data[pos : pos + 1].isspace():
            pos += 1
        if start == pos or pos >= len(data):
            raise FormatError(f"{path}: truncated PFM header")
        tokens.append(data[start:pos])
        if len(tokens) == 1 and tokens[0] != b"Pf":
            kind = "a colour PFM ('PF')" if tokens[0] == b"PF" else repr(tokens[0][:16])
            raise FormatError(f"{path}: expected a grey PFM ('Pf'), found {kind}")
    pos += 1  # the single whitespace byte after the scale
    try:
        width, height = int(tokens[1]), int(tokens[2])
        scale = float(tokens[3])
    except ValueError:
        raise FormatError(f"{path}: bad PFM header {b' '.join(tokens)!r}") from None
    if width <= 0 or height <= 0:
        raise FormatError(f"{path}: bad PFM size {width}x{height}")
    if scale == 0 or not math.isfinite(scale):
        raise FormatError(f"{path}: bad PFM scale {scale}")
    n = width * height
    body = data[pos:]
    if len(body) != 4 * n:
        raise FormatError(
            f"{path}: a {width}x{height} PFM needs {4 * n} bytes of pixels after its "
            f"{pos}-byte header, found {len(body)}"
        )
    vals = array.array("f")
    vals.frombytes(body)
    if (scale < 0) != (sys.byteorder == "little"):
        vals.byteswap()
    rows = [vals[(height - 1 - y) * width : (height - y) * width] for y in range(height)]
    out = array.array("f")
    for row in rows:
        out.extend(row)
    return width, height, out


def read_u32(path, width, height):
    with open(path, "rb") as f:
        data = f.read()
    n = width * height
    if len(data) != 4 * n:
        raise FormatError(
            f"{path}: a {width}x{height} primitive-id image has {4 * n} bytes, found {len(data)}"
        )
    ids = array.array("I")
    if ids.itemsize != 4:
        ids = array.array("L")
        if ids.itemsize != 4:
            raise FormatError("no 4-byte unsigned array type on this platform")
    ids.frombytes(data)
    if sys.byteorder != "little":
        ids.byteswap()
    return ids


def compare(depth_a, ids_a, depth_b, ids_b, tolerance):
    n = len(depth_a)
    hits_a = hits_b = both = same_id = same_hit = both_same_id = 0
    over_tol = over_tol_same_id = 0
    inconsistent = 0  # a depth says hit and the id says miss, or the reverse
    max_rel = max_rel_same = 0.0
    sum_rel = 0.0
    worst = None
    for i in range(n):
        ta, tb, ia, ib = depth_a[i], depth_b[i], ids_a[i], ids_b[i]
        ha, hb = math.isfinite(ta), math.isfinite(tb)
        if ha != (ia != MISS) or hb != (ib != MISS):
            inconsistent += 1
        hits_a += ha
        hits_b += hb
        same_hit += ha == hb
        same_id += ia == ib
        if ha and hb:
            both += 1
            rel = abs(ta - tb) / abs(ta) if ta != 0 else abs(tb)
            sum_rel += rel
            if rel > max_rel:
                max_rel, worst = rel, i
            if rel > tolerance:
                over_tol += 1
            if ia == ib:
                both_same_id += 1
                max_rel_same = max(max_rel_same, rel)
                if rel > tolerance:
                    over_tol_same_id += 1
    return {
        "pixels": n,
        "hits_a": hits_a,
        "hits_b": hits_b,
        "both_hit": both,
        "hit_fraction_a": hits_a / n,
        "hit_fraction_b": hits_b / n,
        "hit_agreement_pct": 100.0 * same_hit / n,
        "primid_agreement_pct": 100.0 * same_id / n,
        "primid_differ": n - same_id,
        "both_hit_same_primid": both_same_id,
        "depth_rel_err_max": max_rel if both else None,
        "depth_rel_err_mean": sum_rel / both if both else None,
        "depth_rel_err_max_same_primid": max_rel_same if both_same_id else None,
        "depth_tolerance": tolerance,
        "depth_over_tolerance": over_tol,
        "depth_over_tolerance_same_primid": over_tol_same_id,
        "worst_depth_index": worst,
        "depth_id_inconsistent": inconsistent,
    }


def main(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("a_pfm")
    p.add_argument("a_u32")
    p.add_argument("b_pfm")
    p.add_argument("b_u32")
    p.add_argument("--json", action="store_true", help="also print one JSON object as the last line")
    p.add_argument("--tolerance", type=float, default=1e-4, help="relative depth error counted as over (default 1e-4)")
    p.add_argument("--min-primid-agreement", type=float, help="fail below this primitive-id agreement, in percent")
    p.add_argument("--max-depth-rel-err", type=float, help="fail when a pixel where both hit the same primitive is off by more")
    args = p.parse_args(argv)
    try:
        wa, ha, da = read_pfm(args.a_pfm)
        wb, hb, db = read_pfm(args.b_pfm)
        if (wa, ha) != (wb, hb):
            raise FormatError(f"{args.a_pfm} is {wa}x{ha} but {args.b_pfm} is {wb}x{hb}")
        ia = read_u32(args.a_u32, wa, ha)
        ib = read_u32(args.b_u32, wb, hb)
    except (OSError, FormatError) as e:
        print(f"compare_images: {e}", file=sys.stderr)
        return 2
    r = compare(da, ia, db, ib, args.tolerance)
    r["width"], r["height"] = wa, ha
    worst = r.pop("worst_depth_index")
    r["worst_depth_pixel"] = None if worst is None else [worst % wa, worst // wa]

    def f(v, spec):
        return "n/a" if v is None else format(v, spec)

    print(f"{wa}x{ha} pixels; hits: A {r['hits_a']} ({100 * r['hit_fraction_a']:.2f} %), "
          f"B {r['hits_b']} ({100 * r['hit_fraction_b']:.2f} %), both {r['both_hit']}")
    print(f"hit/miss agreement {r['hit_agreement_pct']:.4f} %; primitive ids agree on "
          f"{r['primid_agreement_pct']:.4f} % ({r['primid_differ']} pixels differ)")
    print(f"relative depth error where both hit: max {f(r['depth_rel_err_max'], '.3e')} "
          f"(pixel {r['worst_depth_pixel']}), mean {f(r['depth_rel_err_mean'], '.3e')}, "
          f"{r['depth_over_tolerance']} pixels over {args.tolerance:g}; same primitive only: max "
          f"{f(r['depth_rel_err_max_same_primid'], '.3e')}, {r['depth_over_tolerance_same_primid']} over")
    if r["depth_id_inconsistent"]:
        print(f"WARNING: {r['depth_id_inconsistent']} pixels where a depth and its primitive id "
              "disagree about hit or miss")
    if args.json:
        print(json.dumps(r))
    failed = []
    if args.min_primid_agreement is not None and r["primid_agreement_pct"] < args.min_primid_agreement:
        failed.append(f"primitive ids agree on {r['primid_agreement_pct']:.4f} % < {args.min_primid_agreement} %")
    if (args.max_depth_rel_err is not None and r["depth_rel_err_max_same_primid"] is not None
            and r["depth_rel_err_max_same_primid"] > args.max_depth_rel_err):
        failed.append(f"relative depth error {r['depth_rel_err_max_same_primid']:.3e} > {args.max_depth_rel_err:g}")
    for msg in failed:
        print(f"FAIL: {msg}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
