#!/usr/bin/env python3
"""Compare two renderings pixel by pixel: depth (PFM) and primitive ids (raw u32).

    scripts/compare_images.py A.pfm A.u32 B.pfm B.u32 [--json] [--tolerance 1e-4]
                              [--min-primid-agreement 99.9] [--max-depth-rel-err 1e-4]
                              [--ply MODEL.ply --eye x,y,z --look x,y,z [--up x,y,z] [--fov 50]]

A is the reference (Embree in scripts/bench-kernel), B the renderer under test.
The formats are those of bench/embree/README.md, "Output formats":

* depth: grey PFM, header "Pf\\n<W> <H>\\n<scale>\\n" (negative scale = little
  endian), W*H float32 with rows from bottom to top, +inf on a miss;
* primitive ids: W*H raw little-endian uint32, rows from top to bottom,
  0xFFFFFFFF on a miss.

Prints the agreement figures as text, and with --json also one JSON object as
the last line.  The relative depth error of a pixel where both hit is
|tA - tB| / tA.  With --min-primid-agreement and/or --max-depth-rel-err it exits
with status 1 when a figure is worse than the bound (the depth bound applies to
the pixels where both hit the same primitive, or tie).

With --ply and the camera of both renderings, a pixel where both hit different
triangles is checked in double precision: when the pixel's ray hits both
triangles at the same distance (within 1e-6 relative), it is a tie (overlapping
coplanar triangles, or a shared edge) and counts as agreement in
primid_agreement_with_ties_pct (and in the "same primitive" depth figures).
The PLY must be binary little endian with fixed-size records (scalar vertex
properties; faces all triangles), like the models of tests/data and generated plants.

Standard library only.
"""

import argparse
import array
import json
import math
import struct
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


class Triangles:
    """Random access to the triangles of a binary little-endian PLY with
    fixed-size records (for the few triangles the tie check needs)."""

    TYPES = {"char": "b", "int8": "b", "uchar": "B", "uint8": "B", "short": "h", "int16": "h",
             "ushort": "H", "uint16": "H", "int": "i", "int32": "i", "uint": "I", "uint32": "I",
             "float": "f", "float32": "f", "double": "d", "float64": "d"}

    def __init__(self, path):
        self.path = path
        self.f = open(path, "rb")
        if self.f.readline().rstrip(b"\r\n") != b"ply":
            raise FormatError(f"{path}: not a PLY file")
        fmt, elements = None, []
        while True:
            line = self.f.readline()
            if not line:
                raise FormatError(f"{path}: the PLY header has no end_header")
            w = line.decode("ascii", "replace").split()
            if not w or w[0] in ("comment", "obj_info"):
                continue
            if w[0] == "end_header":
                break
            if w[0] == "format" and len(w) > 1:
                fmt = w[1]
            elif w[0] == "element" and len(w) == 3:
                elements.append([w[1], int(w[2]), []])
            elif w[0] == "property" and elements and len(w) >= 3:
                if w[1] == "list" and len(w) == 5:
                    elements[-1][2].append(("list", self._ty(w[2]), self._ty(w[3]), w[4]))
                else:
                    elements[-1][2].append(("scalar", self._ty(w[1]), None, w[2]))
        if fmt != "binary_little_endian":
            raise FormatError(f"{path}: the tie check reads binary_little_endian PLY only, not {fmt}")
        pos = self.f.tell()
        self.vertex = self.face = None
        for name, count, props in elements:
            record, first_list = "<", True
            fields = {}
            for kind, t, item, pname in props:
                if kind == "scalar":
                    fields[pname] = len(record) - 1
                    record += t
                elif name == "face" and first_list:
                    # every face a triangle: count, then three indices
                    fields["count"] = len(record) - 1
                    record += t + item * 3
                    first_list = False
                else:
                    raise FormatError(f"{path}: element {name!r} has variable-size records")
            entry = (pos, count, record, struct.calcsize(record), fields)
            if name == "vertex":
                self.vertex = entry
            elif name == "face":
                self.face = entry
            pos += count * struct.calcsize(record)
        if self.vertex is None or self.face is None or "count" not in self.face[4]:
            raise FormatError(f"{path}: no vertex or face element")
        if any(k not in self.vertex[4] for k in "xyz"):
            raise FormatError(f"{path}: the vertex element has no x, y and z")
        size = self.f.seek(0, 2)
        if size != pos:
            raise FormatError(f"{path}: {size} bytes, but fixed-size records with triangle faces "
                              f"would make {pos}: not every face is a triangle")

    @classmethod
    def _ty(cls, t):
        if t not in cls.TYPES:
            raise FormatError(f"unknown PLY type {t!r}")
        return cls.TYPES[t]

    def _record(self, entry, i):
        pos, count, record, size, _ = entry
        if not 0 <= i < count:
            raise FormatError(f"{self.path}: index {i} out of range (0..{count})")
        self.f.seek(pos + i * size)
        return struct.unpack(record, self.f.read(size))

    def triangle(self, i):
        rec = self._record(self.face, i)
        c = self.face[4]["count"]
        if rec[c] != 3:
            raise FormatError(f"{self.path}: face {i} is not a triangle")
        fx = self.vertex[4]
        return [[float(v[fx[k]]) for k in "xyz"] for v in (self._record(self.vertex, j) for j in rec[c + 1 : c + 4])]


def _sub(a, b):
    return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _normalized(a):
    length = math.sqrt(_dot(a, a))
    return [x / length for x in a]


def hit_distance(tri, origin, d, slack=1e-4):
    """Distance along the ray to the triangle (Moeller-Trumbore, f64, with a
    little slack on the edges), or None."""
    e1, e2 = _sub(tri[1], tri[0]), _sub(tri[2], tri[0])
    q = _cross(d, e2)
    det = _dot(e1, q)
    if abs(det) < 1e-300:
        return None
    s = _sub(origin, tri[0])
    u = _dot(s, q) / det
    r = _cross(s, e1)
    v = _dot(d, r) / det
    t = _dot(e2, r) / det
    return t if u >= -slack and v >= -slack and u + v <= 1 + slack and t > 0 else None


def tie_checker(ply, eye, look, up, fov, width, height):
    """tie(i, id_a, id_b): does pixel i's ray hit both triangles at the same distance?"""
    tris = Triangles(ply)
    w = _normalized(_sub(look, eye))
    u = _normalized(_cross(w, up))
    v = _cross(u, w)
    th = math.tan(math.radians(fov) / 2)

    def tie(i, ia, ib):
        if ia == MISS or ib == MISS:
            return False
        x, y = i % width, i // width
        sx = ((x + 0.5) / width * 2 - 1) * th * width / height
        sy = (1 - (y + 0.5) / height * 2) * th
        d = _normalized([w[k] + sx * u[k] + sy * v[k] for k in range(3)])
        ta, tb = hit_distance(tris.triangle(ia), eye, d), hit_distance(tris.triangle(ib), eye, d)
        return ta is not None and tb is not None and abs(ta - tb) <= 1e-6 * ta

    return tie


def compare(depth_a, ids_a, depth_b, ids_b, tolerance, tie=None):
    """tie(i, id_a, id_b) -> bool, when given, says whether pixel i is a tie."""
    n = len(depth_a)
    hits_a = hits_b = both = same_id = same_hit = both_same_id = ties = 0
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
            tied = ia != ib and tie is not None and tie(i, ia, ib)
            ties += tied
            if ia == ib or tied:
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
        "primid_ties": ties if tie is not None else None,
        "primid_agreement_with_ties_pct": 100.0 * (same_id + ties) / n if tie is not None else None,
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


def vec3(text):
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 3:
        raise argparse.ArgumentTypeError(f"expected x,y,z, got {text!r}")
    return v


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
    p.add_argument("--ply", help="the model both rendered: check differing ids for ties (needs --eye, --look)")
    p.add_argument("--eye", type=vec3)
    p.add_argument("--look", type=vec3)
    p.add_argument("--up", type=vec3, default=[0.0, 1.0, 0.0])
    p.add_argument("--fov", type=float, default=50.0, help="vertical, degrees (default 50)")
    args = p.parse_args(argv)
    if args.ply and (args.eye is None or args.look is None):
        p.error("--ply needs --eye and --look (the camera of both renderings)")
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
    try:
        tie = args.ply and tie_checker(args.ply, args.eye, args.look, args.up, args.fov, wa, ha)
        r = compare(da, ia, db, ib, args.tolerance, tie or None)
    except (OSError, FormatError) as e:
        print(f"compare_images: {e}", file=sys.stderr)
        return 2
    r["width"], r["height"] = wa, ha
    worst = r.pop("worst_depth_index")
    r["worst_depth_pixel"] = None if worst is None else [worst % wa, worst // wa]

    def f(v, spec):
        return "n/a" if v is None else format(v, spec)

    print(f"{wa}x{ha} pixels; hits: A {r['hits_a']} ({100 * r['hit_fraction_a']:.2f} %), "
          f"B {r['hits_b']} ({100 * r['hit_fraction_b']:.2f} %), both {r['both_hit']}")
    print(f"hit/miss agreement {r['hit_agreement_pct']:.4f} %; primitive ids agree on "
          f"{r['primid_agreement_pct']:.4f} % ({r['primid_differ']} pixels differ)")
    if r["primid_ties"] is not None:
        print(f"of the differing pixels, {r['primid_ties']} are ties (both triangles hit at the same "
              f"distance): with them, ids agree on {r['primid_agreement_with_ties_pct']:.4f} %")
    print(f"relative depth error where both hit: max {f(r['depth_rel_err_max'], '.3e')} "
          f"(pixel {r['worst_depth_pixel']}), mean {f(r['depth_rel_err_mean'], '.3e')}, "
          f"{r['depth_over_tolerance']} pixels over {args.tolerance:g}; same primitive{' or tie' if args.ply else ''} only: max "
          f"{f(r['depth_rel_err_max_same_primid'], '.3e')}, {r['depth_over_tolerance_same_primid']} over")
    if r["depth_id_inconsistent"]:
        print(f"WARNING: {r['depth_id_inconsistent']} pixels where a depth and its primitive id "
              "disagree about hit or miss")
    if args.json:
        print(json.dumps(r))
    failed = []
    agreement = r["primid_agreement_with_ties_pct"]
    if agreement is None:
        agreement = r["primid_agreement_pct"]
    if args.min_primid_agreement is not None and agreement < args.min_primid_agreement:
        failed.append(f"primitive ids agree on {agreement:.4f} % < {args.min_primid_agreement} %")
    if (args.max_depth_rel_err is not None and r["depth_rel_err_max_same_primid"] is not None
            and r["depth_rel_err_max_same_primid"] > args.max_depth_rel_err):
        failed.append(f"relative depth error {r['depth_rel_err_max_same_primid']:.3e} > {args.max_depth_rel_err:g}")
    for msg in failed:
        print(f"FAIL: {msg}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
