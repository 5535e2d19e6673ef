"""Write ``docs/performance.md`` from the benchmark results.

    python -m benchmarks.performance_page [--results benchmarks/results.json]
        [--gradients benchmarks/results_gradients.json]
        [--recovery benchmarks/results_recovery.json]
        [--materials benchmarks/results_materials.json]
        [--cuda benchmarks/results_cuda.json]
        [--render-filter benchmarks/results_render_gaussian.json]
        [--render-sampler benchmarks/results_render_multijitter.json]
        [--public benchmarks/results_public_scenes.json benchmarks/results_public_tutorials.json]
        [--out docs/performance.md] [--check]

Reads the JSON files that ``python -m benchmarks`` (intersection throughput,
render time against error, scale), ``python -m benchmarks.gradients`` (gradient
accuracy and step cost), ``python -m benchmarks.recovery`` (transform
recovery) and ``python -m benchmarks.render_error --rfilter gaussian`` and
``--sampler multijitter`` (the render table with Mitsuba's default filter, and with
stratified samples) write, and renders them as Markdown tables with short paragraphs on
how each part is measured and what its targets are. Every measured figure on
the page comes from the JSON; the fixed text holds only the method and the
list of experiments that were tried and not kept (each with the measurement
that decided it), which no results file records.

The page depends on nothing but the JSON: the same files give the same page,
byte for byte (no clock, no machine state, stable ordering). ``--check``
compares instead of writing and exits with status 1 when the page is stale.
The script imports neither ``instancing`` nor Dr.Jit, so it runs anywhere.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

from benchmarks.machine import line as machine_line

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results.json"
GRADIENTS = ROOT / "benchmarks" / "results_gradients.json"
RECOVERY = ROOT / "benchmarks" / "results_recovery.json"
MATERIALS = ROOT / "benchmarks" / "results_materials.json"
CUDA = ROOT / "benchmarks" / "results_cuda.json"
RENDER_FILTER = ROOT / "benchmarks" / "results_render_gaussian.json"
RENDER_SAMPLER = ROOT / "benchmarks" / "results_render_multijitter.json"
#: ``python -m benchmarks.public_scenes --json`` runs: Mitsuba's documentation scenes and its tutorials.
PUBLIC = (ROOT / "benchmarks" / "results_public_scenes.json",
          ROOT / "benchmarks" / "results_public_tutorials.json")
OUT = ROOT / "docs" / "performance.md"
COMMAND = "python -m benchmarks.performance_page"

# The targets the suite is held to (the project's performance issue).
TARGET_PRELIM_RATIO = 1.0       # 1 000 spheres: full record at least Embree's preliminary rate
TARGET_FULL_RATIO = 20.0        # 1 000 spheres: 20x Mitsuba's full ray_intersect
TARGET_FALL = 3.0               # 1 000 -> 100 000 instances: throughput falls less than 3x
TARGET_BUILD_S = 2.0            # 100 000 instances load and build in under 2 s
TARGET_GRADIENT_ERROR = 0.05    # gradient images within 5 % of finite differences


# ---------------------------------------------------------------------------
# Formatting
# ---------------------------------------------------------------------------

def is_number(x: Any) -> bool:
    """True for a finite int or float (NaN marks a figure that was not measured)."""
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def count(n: int) -> str:
    """An integer with thin groups of three digits: 100 000."""
    return f"{n:,}".replace(",", " ")


def fixed(x: Any, digits: int = 2) -> str:
    """``x`` with ``digits`` decimals, or '-' when not measured."""
    return f"{x:.{digits}f}" if is_number(x) else "-"


def sig(x: Any, digits: int = 3) -> str:
    """``x`` to ``digits`` significant figures (98, 1.32, 0.0846), or '-'."""
    if not is_number(x):
        return "-"
    if x == 0:
        return "0"
    decimals = max(0, digits - 1 - int(math.floor(math.log10(abs(x)))))
    return f"{x:.{decimals}f}"


def rate(x: Any) -> str:
    """Mrays/s: two decimals from 1 up, three significant figures below."""
    if not is_number(x):
        return "-"
    return f"{x:.2f}" if abs(x) >= 1 else sig(x, 3)


def percent(x: Any, digits: int = 1) -> str:
    """A fraction as a percentage."""
    return f"{100 * x:.{digits}f} %" if is_number(x) else "-"


def times(x: Any, digits: int = 2) -> str:
    """A ratio as '1.49x'."""
    return f"{x:.{digits}f}x" if is_number(x) else "-"


def span(values: Iterable[float], fmt: Callable[[Any], str]) -> str:
    """'lo - hi' of the finite values (one value alone when they are equal)."""
    finite = sorted(v for v in values if is_number(v))
    if not finite:
        return "-"
    lo, hi = fmt(finite[0]), fmt(finite[-1])
    return lo if lo == hi else f"{lo} - {hi}"


def geometric_mean(values: Iterable[float]) -> float:
    """Geometric mean of the positive finite values (NaN when there are none)."""
    logs = [math.log(v) for v in values if is_number(v) and v > 0]
    return math.exp(sum(logs) / len(logs)) if logs else math.nan


def verdict(met: bool) -> str:
    return "met" if met else "**missed**"


def table(header: Sequence[str], rows: Iterable[Sequence[str]], align: str | None = None) -> str:
    """A Markdown table; ``align`` has one of 'l', 'r' per column (default: first left, rest right)."""
    align = align or "l" + "r" * (len(header) - 1)
    rule = ["---:" if a == "r" else "---" for a in align]
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join(rule) + " |"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def paragraph(text: str) -> str:
    """Fixed text written across lines in the source, joined into one paragraph."""
    return " ".join(text.split())


# ---------------------------------------------------------------------------
# Fixed text
# ---------------------------------------------------------------------------

HOW_MEASURED = """\
`python -m benchmarks` runs the three speed parts of the suite in one invocation, so that
every ratio against Mitsuba 3 is measured in the same run on the same machine, and writes
`benchmarks/results.json`: intersection throughput (`benchmarks/intersect.py`), render time
against error (`benchmarks/render_error.py`) and scaling to a million instances
(`benchmarks/scale.py`). `--parts` re-runs some parts and keeps the others' entries; `--quick`
runs everything at a small size (a smoke test, never mixed with full results). Gradient
accuracy and cost (`python -m benchmarks.gradients`) and transform recovery
(`python -m benchmarks.recovery`) have their own entry points and files. The console logs of
the runs are kept beside the JSON as `benchmarks/results_*.txt`. Each timed figure is a
median of repeated runs after a warm-up run that also compiles the kernels. The benchmark
machine has two cores and is shared: Mitsuba's own figures move by 10 - 30 % from one run to
the next, so ratios within about 10 % of 1 are parity, not a result; where a ratio between two
sizes matters, the scripts also time the two in alternation; the intersection table times
ours and Embree's preliminary query in alternation in every row."""

INTERSECT_METHOD = """\
`scene.intersect` returns the full hit record (t, p, n, instance, prim). It is timed against
Mitsuba's `ray_intersect_preliminary` (Embree; t and ids only) and its full `ray_intersect` on
the same instances (one `shapegroup` holding the model, one `instance` per copy) and the same
random rays (origins inside the scene's bounds, isotropic directions). Every kind but the
sphere is randomly rotated. The field keeps its 20-unit box and shrinks the sizes as
N^(-1/3), a constant volume fraction: the box's optical depth grows as N^(1/3), so more of the
random rays hit something (last column) and the work per ray grows with N. "grid" and "BVH"
are our two structures forced; "ours" is the one the scene builder picks ("unrolled": up to 12
instances tested one after the other, no structure); "t+ids" is its first phase alone (t,
instance and primitive position, before the float64 record), like for like with Embree's
preliminary query. Mitsuba's full `ray_intersect` gets a
single call and only up to 1 000 instances (it re-traces one callable per instance on every
call); "-" marks what was not measured. The clustered row holds a few dense clusters in a
large empty box, where the builder switches to the BVH."""

RENDER_METHOD = """\
Both renderers render the same scene (exported with `instancing.to_mitsuba`: plain shapes
where Mitsuba accepts every transform, `shapegroup` + `instance` otherwise) at a reduced film
size for spp = 1, 2, 4, ...; the time is the median wall time of the renders after a warm-up
render at the same spp (ours replays the warm-up's `dr.freeze` recording, `render`'s default),
with the clock stopped once the image is in NumPy. The error is the relative RMSE,
`sqrt(mean((img - ref)^2)) / mean(ref)` over all pixels and channels, against a Mitsuba
reference rendered with distinct seeds. Equal error: the error Mitsuba reaches at the target
spp (or at the highest spp it reached within the time cap); each renderer's time at that error
is interpolated between the measured spp in log(time)-log(error), and the speed-up is
Mitsuba's time over ours (> 1: we are faster). That first crossing reads one point of each
curve, and a curve that a few bright pixels (fireflies) dominate rises and falls from one spp
to the next, so it also gives the variance model's speed-up, which uses every spp: an unbiased
renderer's expected squared error at n spp is the reference's noise squared plus V / n, each
spp gives an estimate of the variance per sample V, and V is their median (over the spp whose
error is not mostly the reference's noise); Mitsuba at the target spp and ours at target spp x
V(ours) / V(Mitsuba) then have equal expected error, and the speed-up is the ratio of the
times interpolated there. On well-behaved curves the two agree. The error floor is each
renderer's error at its highest spp: a floor well above the other's would show a bias between
them. Target: the equal-error time at most Mitsuba's in every row: every bundled scene with
`direct`, and with `path` the multi-model scenes (affine_shapes, cornell_box, forest,
showcase, sphere_field) and the 100 000-triangle terrain, and with `volpath` the
participating-media scenes (fog, plume, smoke, subsurface, window)."""

RENDER_ESTIMATORS = """\
Comparing at equal error rather than at equal spp accounts for the estimators differing: our
`direct` traces a shadow ray to every point and directional light where Mitsuba picks one
emitter per sample, and finds the constant environment by the cosine-weighted BSDF sample
alone, so ours costs more per sample on some scenes and has less variance. The table below
separates the two effects: the time per render at the target spp (equal samples) and the error
of a 1-spp render."""

SCALE_METHOD = """\
N sphere instances (the uniform field of the intersection benchmark), each N in a fresh
process with an empty kernel cache (so "first image" includes the LLVM compilation a new
machine pays), then a second short process with the now warm disk cache (the first image a
returning user sees). A camera looks at the field, lit by one directional light; `direct` at
the size and spp below. Parse and build split `load_scene`'s wall time. Later frames and later
optimisation steps replay the first call's `dr.freeze` recording; "kernels compiled" counts
the JIT launches that missed the in-memory kernel cache. Memory per instance is counted two
ways: the growth of the resident set from before `load_scene` to after the first render (the
slope between consecutive N, since fixed costs such as LLVM and the compiled kernels weigh on
small N), and the bytes the scene holds, found by walking every Dr.Jit and NumPy array
reachable from the Scene object. An optimisation step (`instancing.OptimisationStep`: update,
render, L2 loss, `dr.backward`, Adam step) differentiates the translations of 8 instances."""

GRADIENT_METHOD = """\
Gradient images of one instance of every model kind (ellipsoid, sheared cube, rectangle,
reflected disk, non-uniformly scaled cylinder, reflected torus mesh, each rotated) in front of
a wall, with respect to its translation, rotation and scale, against central finite
differences of high-spp renders with the same random numbers (sample counts and steps in
`benchmarks/gradients.py`). Error: the mean over the non-zero pixels of
`|a - r| / max(|r|, 0.2 max|r|)`."""

GRADIENT_SHADOW = """\
The same with the lamp moved off the camera, so that the object's shadow on the wall is in
view, with the shadow-boundary term (`sppi`). The target: an error of at most 1.5x the finite
differences' own seed-to-seed spread (two central differences with different seeds) and at
most 5 %."""

GRADIENT_SHADOW_PATH = """\
The same in `path` (max_depth 3): the wall shows the object's shadow directly and, lit by the
light bounced off the object and the wall, the shadow's edges by one bounce (the hard shadows
seen from the path's vertices), with every term on (`sppi` 1 024) and, for comparison, with
`sppi` 0; the torus mesh's interior term at 8 192 spp (its paths bounce on it twice, the
noisiest of these). Central differences at 16 384 spp; same target."""

GRADIENT_MITSUBA = """\
The gradient of a plain shape's translation (a similarity-scaled sphere, the sheared cube, the
rectangle; Mitsuba cannot differentiate instances) in front of the wall with the point light off
the camera, {size}x{size}, at several sample counts: ours (`direct`, sppc = sppp = sppi = spp)
beside Mitsuba 3.9.1's `direct_projective` (the same counts, forward mode), in one process,
each timed (median of 3 after a warm-up) and compared with one central difference of our
renders at 16 384 spp. Mitsuba's projective sampling finds no shadow boundaries of point
lights (it says so), so its error stops at the bias of that missing term."""

GRADIENT_MITSUBA_AREA = """\
The same comparison with the point light replaced by a rectangle area lamp off the camera
(`python -m benchmarks.gradient_mitsuba --light area`): both renderers sample the soft shadows'
boundaries (ours: the secondary boundary term; Mitsuba: projective sampling from the shading
points), {size}x{size}."""

GRADIENT_MITSUBA_AREA_PATH = """\
The area-lamp comparison in `path` (`python -m benchmarks.gradient_mitsuba --light area
--integrator path`): ours `path` beside Mitsuba's `prb_projective`, both with max_depth
{max_depth} (the wall lit directly and by one bounce off the object), forward mode,
{size}x{size}; both sample the soft shadows' boundaries from the paths' vertices; the central
differences of our `path` renders at 16 384 spp. (Mitsuba's projective integrators find no
shadow boundaries of point lights, so the point-light scene has no `path` row.) Mitsuba's time
hardly grows with the samples at this film size: about 3 s of each of its gradient images is a
fixed cost per render, so on larger films the time ratios would be smaller than here."""

GRADIENT_CONTACT = """\
Each model kind sinking into a floor (a rectangle); a turned cube and an ellipsoid sinking into
a box's top face ("in box"), a floor of mesh tiles (32 coplanar triangles, "in tiles") and the
faceted top of a big mesh sphere ("in boulder"); a cube, an ellipsoid and an elliptic cylinder
sinking into the top of a big sphere ("in dome") and of a big cylinder lying on its side ("in
drum"), where the ellipsoid and the cylinder meet the receiver along the curve where two
quadrics meet; seen from above at an angle with the light at the camera: where they meet, the
camera sees one surface end at the other. Same error measure and target as with shadows in
view; central differences at 8 192 spp."""

GRADIENT_TOUCHING = """\
Light bounced between an instance and the floor it stands in, in `path` (`max_depth` 3), lit
from the side: an upright panel moved along its normal and turned about the vertical, and each
model kind of the contact cases sinking and turned. Near their contact line, paths bounce
between the two surfaces at every distance down to 0, where holding the next vertex fixed
makes the interior term's variance infinite; path replay's slide moves a near next vertex
with the previous one ([interior term](differentiable-rendering.md#interior-and-boundary-terms)).
Ours at 4 096 spp (two seeds: "our spread"), central differences at 16 384 spp; "without" is
ours with the slide switched off. Same target as the moving mirrors below."""

GRADIENT_DEPTH = """\
One reverse-mode `path` gradient step (render, L2 loss, `dr.backward`) of the Cornell box with
its tall box moving, at {size}x{size} and {spp} spp, at several `max_depth`, each in its own
process (peak resident set, which includes Python, Dr.Jit and Mitsuba): path replay, whose
derivative pass replays each path in a second symbolic loop, beside the evaluated bounce loop
it replaced (run in the same benchmark from that revision), which kept every bounce's state
for the backward pass."""

GRADIENT_DELTA = """\
Moving mirrors and glass, which path replay follows through chains of delta lobes (the vertex
after a delta lobe moves with the ray the lobe sends from the moving surface), under a smooth
environment map, 16x16; and a glossy bounce: a rough metal floor reflecting a spot's highlight
onto a diffuse panel moving towards the camera, where the floor's BSDF must see the panel's
vertex move; and an ellipsoid moving over a mirror floor and over a smooth plastic one, whose
reflected silhouettes are sampled from the camera's mirror image. Ours at 16 384 spp (two seeds: "our spread"), central differences at 65 536 spp;
the target is the error at most 1.5x the two estimates' spread (the root mean square of ours
and the differences') and 5 %. The glass cube shows edges through itself, whose jumps no term
samples, and the glass ellipsoid's interior term is heavy-tailed near total internal
reflection ([limits](differentiable-rendering.md#limits))."""

GRADIENT_LIGHTS = """\
Moving lamps against central differences, same error measure and target as with shadows in
view: a point light's position and a directional light's direction over the sheared cube
(shadows in view), and an area-emitting rectangle and sphere (non-uniformly scaled) moved and
turned in front of the wall, with nothing between lamp and wall."""

GRADIENT_PENUMBRA = """\
Soft shadows in view: the validation scenes lit by an area lamp off the camera (a rectangle or
a sphere, non-uniformly scaled, at (1.5, 1.5, -3)) or by the uniform environment instead of
the point light; `direct` and `path` (max_depth 3), same error measure and target as with
shadows in view; ours with the secondary boundary term (`sppi` 1 024; 4 096 for the torus mesh)
and without it (`sppi` 0). Central differences at 16 384 spp (`direct`) and 8 192 (`path`)."""

GRADIENT_INTERREFLECTION = """\
Interreflection: each closed model hangs above the camera's view, lit from below by a
directional light (its shadow falls out of view), so the wall shows it only by one diffuse
bounce (`path`, max_depth 3); its translation's gradient image against central differences
with a 0.03 step at 65 536 spp (a smooth field under path-tracing noise)."""

GRADIENT_REFLECTED = """\
Shadows seen only by one bounce: a lamp over a floor, the object under it, and a screen below
the object and beside it, facing down (the lamp lights only its back); the camera sees the
screen, which shows the floor's shadow by diffuse interreflection. Under a small rectangle
lamp ("area") the penumbra's motion is a visibility change seen from the path's second vertex;
under a point light ("point") the light that the floor gathers jumps at the hard shadow's
edge, a curve seen from the screen, the path's first vertex (`path`; with max_depth 5 the
later vertices too). No path that reaches the camera meets the object: the derivative is the
secondary term alone ("without": `sppi` 0). The object's translation at {size}x{size}
against central differences: area, a 0.1 step at 262 144 spp, ours at 1 048 576 sppi; point,
a 0.05 step (0.025 for the torus; the hard shadow's image curves more) at 1 048 576 spp, ours
at 262 144 sppi; ours at 65 536 spp for the interior."""

GRADIENT_COST = """\
One optimisation step (update the parameters, render `direct` with the boundary term, L2 loss,
`dr.backward`, Adam step; ours one recorded `instancing.OptimisationStep`) with every sphere's
translation differentiated, beside Mitsuba's `direct_projective` (`sppi` 0) on the same spheres
as plain shapes (Mitsuba cannot differentiate instances). Each configuration runs in three
processes per renderer, ours and Mitsuba's in alternation, each process timing the median of 3
steps after 3 warm-up steps; the table gives the median over the processes (a renderer that
fails or times out is not run again) and the largest peak resident set, which includes Python,
Dr.Jit and Mitsuba themselves."""

RECOVERY_METHOD = """\
`scenes/recover_init.json` -> `scenes/recover_target.json`: three non-uniformly scaled
instances (a cube, a rectangle and a torus mesh) moved, turned and rescaled, recovered by
`instancing recover` (Adam on translation, rotation and scale, a fresh seed per iteration).
Errors: translation over the instance's size, rotation in degrees, the largest relative scale
error; targets 1 % of the size, 1 degree and 1 %."""

RECOVERY_SHADOW = """\
With shadows in view: the same scenes with the lamp moved from the camera to ({light}), so
that every instance's shadow on the ground is in view, recovered with the shadow-boundary term
(`sppi`, the default) and without it (`sppi=0`); final errors:"""

RECOVERY_COARSE = """\
Coarse to fine: the box alone moved by 1.5 times its size, so that it no longer overlaps its
target; plain descent against a loss blurred by a Gaussian that shrinks to nothing over the
first half of the run (same iterations and seeds). Translation error over the size:"""

# Measurements from instrumented or one-off runs that explain the tables; no results file
# records them, so they stay here as text.
FINDINGS = """\
## Why the figures are what they are

These come from instrumented or one-off runs, not from the results files.

* **The fall from 1 000 to 100 000 instances** has two measured causes. The field's growing
  optical depth: instance tests per sphere ray grow from 8.0 to 14.6 and grid-walk iterations
  from 10.4 to 18.4. And memory: with the walk limited to 2 cells per ray (the same work at both
  sizes), 100 000 spheres are still 2.0x slower, since every lane's instance rows and grid cells
  come from L3 (about 8 MB touched at random), not from the 1.25 MB L2. Sorting the rays by
  where they enter the grid attacks the second cause (at 1 000 000 spheres it speeds phase 1 up
  1.40x, 575 -> 412 ms per 2^20 rays; the sort costs about 40 - 50 ms per 2^20 rays, which is
  why scenes below 6 MiB of walk data skip it). The first cause weighs more on the flat shapes:
  a disk blocks half the rays a sphere of its radius blocks, so at 1 000 instances most rays
  leave the 16-cell grid unhindered, and at 100 000 they walk about twice as many of the 74
  cells before a hit as through the spheres.
* **Meshes** trace below Embree's rate: the lanes of a packet wait for its slowest ray, and
  a BVH step of the masked loop is about 220 LLVM IR operations for the packet (the slab
  tests, the stack, the loop's masks and branches; halving its loads by 16-bit nodes changed
  nothing). Random rays through 10 tori: 28 % enter a torus's box and then take 6.9 steps
  and 1.3 triangle tests each, at least 2.1 - 2.2 packet iterations per ray at 4, 8 or 16
  lanes alike. Walked one instance after the other, a 16-lane packet of those rays entered
  3.7 instances' walk loops, each for the one or two of its lanes in that box; walked
  nearest box first, in rounds, it runs 1.4 (phase 1 1.36x faster). Even with every lane
  in a torus's box (rays aimed at one torus), the walk takes 2.5x Embree's time.
  Embree tests 4 or 8 boxes per step, one ray at a time, with no lane waiting for another.
  What a step's parts cost, by adding to it (2^20 random rays through one torus, phase 1,
  69.6 ms): 6 / 12 more masked gathers (from a copy of the nodes, each result kept by a
  select) 76.9 / 81.5 ms, about 1 ms per gather per step, so the 12 box coordinates are
  about a sixth of the walk; a dependent chain of 20 multiplications and 20 additions
  7.4 ms more (another run, 70.1 -> 77.4 ms); one more write and read of the walk's stack
  (local memory at a per-lane slot) 9.3 ms more (71.5 -> 80.8 ms). How busy the lanes are,
  from per-ray step counts (2^20 rays, 16-lane packets; lane steps over the packets' longest
  walks): rays aimed at one torus 9.1 steps per ray, the longest of a packet 23.2, 39 % of
  the lanes busy; random rays through one torus 6.6, 23.0, 29 %; through 10 tori 1.9, 15.1,
  13 %. Spending a packet's iterations otherwise did not make the walks faster (two variants
  in the tried list below), nor did wider packets: the time follows the busy lanes' steps,
  about 15 ns of one core per lane step even with rays aimed at the torus. The two levels
  cost little of it: the tori's triangles baked into one world-space BVH (an experiment,
  2^20 random rays, full record, in alternation) trace 10 tori in 60.8 ms against 61.0 ms
  instanced, 1 000 tori in 404 against 452 ms; the walk itself is what trails Embree.
  Sampled by `perf` over the kernel's machine code (10 tori, 2^18 random rays, phase 1 on
  one thread, 33 948 samples): the step's 12 box-coordinate gathers with their slab tests
  take 35 % of the samples, the children's references (a 64-bit load per lane) 4 %, ordering
  the children and the stack's push and pop 15 %, the loop's head 5 %, the leaves' triangle
  tests 15 %, the top level's rounds (each ray into its picked instance's space) 12 %, and
  Python with Dr.Jit's launches 14 %. No instruction holds more than 8 % (the one after a
  node's first gather, which waits for the node's cache line), and 31 of the kernel's
  instructions reload loop values spilled to the stack: the step's cost is spread over its
  200-odd instructions.
* **Mitsuba scenes made of meshes** are where users meet the mesh walks first: the `bsdf`
  files of Mitsuba's example scenes (its material-preview mesh, 57 152 triangles, in each
  material) and the tutorials' LEGO scene (441 bricks, each its own mesh, 2.0 million
  triangles) are the slowest groups of the table above. On the material-preview scene
  (`bsdf_diffuse_plain.xml`, 64x48, 256 spp, in alternation) a `path` render takes 687 ms
  against Mitsuba's 309 ms, its camera rays' first hits alone 69 ms; each bounce beyond the
  first costs about 155 ms against Mitsuba's 57 ms (`max_depth` 2 / 3: 344 / 499 ms
  against 188 / 244 ms), and 2^20 random rays among its three meshes take 234 ms for our
  full record against 77 ms for Mitsuba's: the mesh walks are the difference. Baking its
  three meshes into one world-space BVH made those rays slower (64 -> 83 ms through the
  whole scene's bounds), and its top-level choice does not matter (unrolled 242 ms, BVH
  246 ms, grid 299 ms). On the LEGO scene (256x192) the camera rays'
  first hits (`aov` depth, 4 spp) take 46.4 ms through our two levels (the grid `auto` then picked over the
  bricks' overlapping boxes, then each brick's BVH) and 21.7 ms with all triangles baked
  into one world-space BVH (the same pixels hit, median depth difference 0; an experiment,
  not in the package); 2^20 random rays 1 333 -> 580 ms. Re-braiding (Benthin et al.,
  "Improved Two-Level BVHs using Partial Re-Braiding", 2017: each brick entered at up to 16
  or 128 subtrees of its own BVH, each with its world box, in the top level) took phase 1
  of those rays only from 1 198 to 1 024 ms (16) and from 1 203 to 1 007 ms (128) through
  a top-level BVH, about what the BVH alone gains there, and 1.01 - 1.02x through the grid:
  the baked tree wins by the SAH splitting the bricks' triangles across bricks, which a
  two-level tree cannot. Such a tree needs an SAH build over 2 million triangles: 5.7 s
  with the meshes' Dr.Jit build (28 s with the NumPy build before it; clusters of 32 or 8
  items in Morton order with the SAH above them built it in 10 - 11 s, but traced 1.16 -
  1.19x slower), and world-space triangles would give up the object-space float32 that
  keeps hits independent of where a scene lies. Loading the scene takes 5.5 - 5.9 s
  against Mitsuba's 2.3 - 2.5 s (in alternation; 12.3 s with the NumPy build): reading its
  439 PLY files about 1 s, the meshes' SAH trees, built together, about 3 s, of which
  about 1.7 s are the build's kernels. Since the top level walks in nested loops (a
  top-level BVH, in alternation, 2^19 random rays through the scene's bounds): phase 1
  328 ms against Embree's 76 ms (4.3x), shadow rays (any hit) 218 against 50 ms (4.4x); a
  `path` render at 64x48, 256 spp: camera rays 132 against 56 ms (`max_depth` 1), each of
  the next two bounces 158 / 131 against 58 / 38 ms (the bricks' materials are all diffuse).
* **Mitsuba's participating-media scenes** (`volpath`) are the slowest of its example scenes
  here, and the shadow rays are why: on `test_homo_emitter_inside_medium_volpath.xml` (64x48,
  256 spp, `max_depth` 6; two thin-dielectric spheres holding a dense medium, sigma_t 5, a
  torus lamp inside, an environment) a render takes 4.9 s against Mitsuba's 1.2 s, 3.5 s of
  it the shadow rays' transmittance (1.4 s with it set to a constant, 2.2 s with each shadow
  ray an any-hit query). A camera sample makes 5.1 queries along its path and 5.7 along its
  shadow rays (one to the environment and one to the lamp at every scattering event, where
  Mitsuba's volpath draws one of the two), all in one kernel of 10 337 operations whose
  16-lane packets run each query as long as their slowest lane: about 1.2 us of a core per
  sample and query. Phase 2 of the shadow rays' hits is 8 % of the render (5.6 s without
  it): the mesh walks again. All twelve of these scenes stand on Mitsuba's dome
  (`sphere_base.obj`), a fan of 5 632 slivers (box excess 11 at the median) whose boxes are
  mostly empty; built over split triangle references (docs/how-it-works.md, "Acceleration"),
  it takes half the walk (2^20 random rays in its bounds 469 -> 205 ms; Embree 86 ms), and the
  twelve render 1.22 - 1.51x faster (64x48, 256 spp, median of 3, on an Intel Xeon of 2 cores;
  against Mitsuba in the same runs: the heterogeneous-media scenes 1.23 - 2.29x -> 1.00 -
  1.55x its time, the homogeneous ones 2.60 - 8.05x -> 1.89 - 5.79x). Russian roulette of
  faint shadow rays, whose queries then stop where the ray would, and paths' queries cut at
  their drawn free-flight distance (docs/rendering.md, "Participating media") took the
  homogeneous-medium scenes' time at equal error down by up to 2x (1.0 - 2.0x; sweep in
  docs/how-it-works.md, "Tuned constants"); in the table above the twelve take 0.97 - 1.60x
  Mitsuba's time at equal error (heterogeneous media) and 1.38 - 3.24x (the others).
* **Few instances and rays that mostly miss** are Embree's ground: with 10 instances there is
  little traversal to win, and the clustered field's rays nearly all miss: Embree's wide
  nodes reject most of them at its root, while our binary BVH tests its frontier (8 boxes)
  before the loop. Fixed costs are most of Embree's whole time on this row (3.5 - 4.8 ms per
  2^20 rays): tracing our query takes 0.65 ms per call, and a kernel that only reads 2^20
  rays and writes a record of that size 1.3 - 1.7 ms. Of the random rays, 0.3 % meet a
  frontier box; their walks through the clusters (19.5 loop iterations on average, median
  13, testing 0.75 spheres) take 2.9 ms of the kernel's 4.5 ms, each in a packet of its
  own: 13 465 such walks cost 10.4 ms of kernel time one per packet and 3.5 ms packed 16 to
  a packet, but packing them takes kernels of their own (tried list). What the 10-instance rows compare is our full record against
  Embree's preliminary one: our phase 1 alone, which returns what Embree's preliminary query
  does (t and ids), is faster than it on every analytic kind, and the float64 phase 2 (the
  winner re-intersected in object space, its world point and normal) makes up the
  difference where phase 1 has little to spare: tested nearest box first, in rounds, their
  full records come out ahead. The rounds are one symbolic loop, traced once: unrolled,
  one branch per round, they took 9.7 ms to trace for 10 tori (1.4 ms as a loop) and
  0.9 ms for 10 spheres (0.4 ms), on every call of `scene.intersect` (Embree's whole query
  takes 3.5 - 15 ms on these rows). One run before the slab tests by compare and select and the opaque unrolled
  rows (which took phase 1 of these rows 1.5 - 1.9x faster, the table has today's
  ratios), 2^20 random rays, ours and Embree alternating, ms (phase 1 / full record /
  Embree): rectangles 12.3 / 18.5 / 14.1, disks 10.0 / 15.0 / 18.2, cylinders
  15.2 / 23.6 / 22.6, cubes 17.7 / 27.8 / 27.5, spheres 15.6 / 25.4 / 19.0; tori
  105.5 / 117.7 / 19.8 (the mesh walk itself). Where phase 2's time goes, 2^20 random rays,
  median of 7 in alternation, ms (phase 1 / full record with only t evaluated / t, instance
  and prim / the full record): spheres 13.5 / 18.6 / 18.9 / 21.3, rectangles 10.7 / 14.6 /
  14.6 / 15.7, cylinders 13.3 / 18.2 / 18.2 / 20.3, cubes 16.7 / 21.9 / 21.4 / 25.9: about
  5 ms is the float64 re-test itself, a branch that nearly every 16-lane packet takes (10 -
  20 % of the rays hit), and 1 - 4 ms writing the world point and normal. Leaving out the
  error bound, the shading frame, the grazing-hit fallback or even the float64 inverse
  changes the full record by less than the noise (0.1 - 0.6 ms): what is not evaluated is
  not computed, and the rest is latency of the float64 chain. On the current code (10
  spheres, phase 2 as a kernel of its own): 7.9 ms phase 1, 6.2 ms phase 2, of which the
  float64 quadric test with its re-projected point takes 2.5 ms and the normal's
  normalisation 0.7 ms; its inverse gathered instead of computed changes nothing.
* **Mitsuba's full `ray_intersect` with instances** re-traces one callable per instance on
  every call: 12 - 40 s per call at 1 000 instances; at 10 000 a single call ran for over
  20 minutes and grew past 22 GB, so it is not measured there.
* **The subsurface `volpath` row** (a glass sphere and a rough glass cube filled with
  scattering media, lit by a small lamp) measures fireflies: light reaches the media only
  through the glass, by paths that find the lamp by chance, so both renderers' errors stay
  near the reference's own noise and rise and fall from one spp to the next. Its first
  crossing is read where one of Mitsuba's render sets happened to miss the fireflies; the
  variance model, which pools every spp, is the row's measure. At 64x48 and 256 spp, ours has
  0.64x Mitsuba's block error (`tests/test_mitsuba_render.py::test_medium_scenes_match_mitsuba`).
* **Optimisation steps of large sphere fields** look, each step, for what the moving
  instances change besides their silhouettes (the boundary terms of
  docs/differentiable-rendering.md): the shadows they cast and receive, and their contact
  curves with the spheres they cut. The scale table's random fields overlap (380 000
  touching pairs at 1 000 000 spheres), and a step there once took 24.0 s: every overlapping
  pair was found before the moving ones were kept, and a moving sphere's box swept towards
  the light was bounded by an axis-aligned span that held most of the field (56 117 casters
  of 100 000 spheres). The moving instances' boxes are now paired with the others directly,
  and the casters are the boxes that meet the swept box itself (199 of 100 000, 496 of
  1 000 000). Later steps at 1 000 / 10 000 / 100 000 / 1 000 000 spheres took 0.92 / 1.76 /
  3.54 / 24.0 s before and take the times in the table above; most of a step at 1 000
  spheres is the boundary terms' kernels (each term, silhouettes, shadows and contacts,
  evaluates the integrator on both sides of sppp samples per pixel).
* **Mitsuba's 1 000-sphere gradient steps** compile kernels for minutes on their first use
  with 1 000 shapes (Dr.Jit keeps compiled kernels on disk, so later processes skip that);
  the warm-up steps absorb it, and where a process runs past the per-process limit (600 s)
  the cost table says so."""

TRIED = """\
## Tried and not kept

Each with the measurement that decided it (kernel time at 128x96, or Mrays/s of the full hit
record on 2^20 random rays; "1 000 / 100 000" are sphere fields).

Meshes and the forest:

* triangle references (split slender triangles) for every mesh with triangles of box excess 6
  or more, without the surface-area choice between them and the triangles: the forest at
  256x192, `path` 4 spp / `direct` 16 spp, 233 / 285 -> 249 / 306 ms and 240 / 287 -> 263 /
  315 ms, the showcase `direct` 16 spp 57 / 60 -> 65 / 67 ms (in alternation): the low-poly
  tree's split triangles (1.5 references each) cost more than they save, as its surface cost
  says (1.15x its triangles'); a teapot's 1.03x;
* the references' cuts at the planes of the mesh's Morton grid (the coarsest power-of-two plane
  inside a piece's box, as Karras and Aila) instead of at the midpoint of its longest side:
  2^20 random rays in the bounds of Mitsuba's participating-media dome, a reference per 4 /
  3 / 2 of box excess (no budget), 240 / 228 / 218 -> 260 / 239 / 231 ms;
* the mesh rounds of unrolled scenes each in a branch of its own after the previous one
  instead of nested in it (a packet then tests every round's pick, whether or not any lane
  has a box left): 2^20 random rays through 10 tori, phase 1 1.24x faster than one walk
  per instance, against 1.36x nested (each in alternation with the walks one after the
  other, another job running);
* the meshes' BVH walked in one flat loop (a triangle test or a step per iteration) instead
  of the nested step and triangle loops, on random rays: 10 / 1 000 tori 56.5 / 463.9 ->
  54.6 / 481.4 ms for phase 1 (hits identical): within noise;
* a 4-wide BVH (the binary SAH tree collapsed, four boxes per step as six float4 loads,
  children sorted by a 5-exchange network): forest `path` at 4 spp 188 -> 211 - 220 ms,
  light_area equal; again on the current walk (the four boxes by masked scalar gathers,
  nested step and triangle loops, hits identical), 2^20 random rays in alternation, phase 1
  / full record: 10 tori 45.8 / 50.2 -> 47.2 / 51.5 ms with the children sorted, 44.3 /
  49.1 -> 47.6 / 51.6 ms with only the nearest moved first; 1 000 tori 294.5 / 301.4 ->
  310.5 / 313.8 ms: the steps halve, but each costs about twice as much;
* testing a leaf's next triangle and taking the next BVH step in the same loop iteration:
  forest `path` 229 / 236 -> 252 / 245 ms; again on 2^20 random rays through 10 / 1 000 tori:
  116.9 / 642.9 -> 116.3 / 615.0 ms (within noise);
* the frontier (the top 8 subtrees' boxes tested before the loop, kept for the top level) for
  the meshes' BVHs too: 10 / 1 000 tori 119.6 / 735.9 -> 122.2 / 738.3 ms per 2^20 rays;
* packets of 4 lanes for mesh scenes instead of 8: 10 tori 79 - 94 ms against 82 - 87;
* packets of 8 lanes for every kernel of a scene with meshes (Dr.Jit's default is 16 on
  AVX-512), which had taken 2^20 random rays through 10 / 1 000 tori from 111 - 125 /
  678 - 703 to 82 - 87 / 570 - 594 ms when mesh walks cost more: once the slab tests were
  compare-and-select and the unrolled rows opaque, renders at 128x96 ran 1.10 - 1.36x faster
  at 16 lanes (light_area `direct` / `path` 64 spp 38.8 / 92.8 -> 28.4 / 76.2 ms, terrain
  `path` 263.9 -> 225.9, showcase `direct` 103.0 -> 80.5; forest `path` 16 spp equal),
  camera-like rays 1.12 - 1.37x and random rays through 1 000 - 100 000 tori 1.02x; only
  random rays through 10 tori were faster at 8 (77.7 against 87.6 ms): the narrow width was
  removed;
* the BVH step without nested branches (selects and masked stack writes): equal within noise;
* SAH traversal costs 0.5, 2 and 4, and leaves of up to 8 triangles: none better than cost 1
  with leaves of up to 4;
* one loop over the grid's cells, their instances and the meshes' BVH nodes instead of a mesh
  walk nested in the grid walk (images bit-identical): forest `direct` at 16 spp
  264 -> 407 ms;
* leaving outsized instances (the forest's ground) out of the grid: 274 -> 348 - 361 ms;
* the grid at 2, 8 or 16 cells per instance on the forest: 300, 287, 297 ms against 277 ms
  at 4;
* a leaf's triangles (up to 4) tested in the loop iteration that reaches it, masked by its
  count, instead of one per iteration: 2^20 random rays through 10 / 1 000 / 10 000 torus
  instances, in alternation, 8.36 / 1.40 / 0.88 and 8.53 / 1.55 / 0.91 Mrays/s without,
  8.11 / 1.53 / 0.95 and 8.78 / 1.54 / 0.93 with: within noise;
* Embree for the meshes themselves (the model in a Mitsuba scene of its own, queried with
  `ray_intersect_preliminary` in object space below our top level, one masked call per
  instance whose box the ray meets): 10 tori, 2^20 random rays, in alternation, 47.8 Mrays/s
  for t and ids against 14.1 for our full record and 58.7 for Embree's own instancing; not
  kept because Embree, as Mitsuba builds it, is not watertight: of 20 000 rays through the
  icosphere's shared edges and vertices (`tests/test_mesh_model.py`), 92 missed it
  and 1 656 hit a surface behind the first (0 and 0 with our walk); sheared and reflected,
  19 and 594. With Mitsuba's `embree_use_robust_intersections` (Embree's robust mode) on the
  same rays in object space: 0 misses, but 2 of the 20 000 still hit the far side (identity
  case; 0 and 0 sheared and reflected), so still not watertight;
* the meshes' BVH nodes quantized to 16 bits per coordinate in the mesh's box (two uint4
  loads per step instead of three float4 and one uint2 load, the ray mapped into the
  quantized frame once per walk; hits identical): 10 / 1 000 tori 84.4 / 561.2 -> 84.4 /
  559.5 ms per 2^20 rays: the loads are not what a step costs;
* a BVH node's 12 box coordinates read as three float4 packet loads (one vector load per
  lane and a transpose, for every lane of the packet; the layout of the nodes until the
  scalar gathers, masked to the lanes taking a step, replaced it): 2^20 random rays, phase
  1, in alternation, 1 / 10 / 1 000 tori 69.1 / 52.4 / 426.5 ms with the gathers against
  75.0 / 56.2 / 459.2 with the packets, hits identical;
* the triangle corners by nine masked scalar gathers as well, instead of two float4 packet
  loads and one gather: 2^20 random rays, full record, median of 9 in alternation, 1 / 10 /
  1 000 tori 0.99 / 1.02 / 1.01x, renders (forest and terrain `path` 4 spp, showcase
  `direct` 16 spp) 1.01 / 1.00 / 1.00x: within noise;
* node boxes read by the ray's direction signs (each axis's near and far planes gathered
  at per-lane offsets, the slab test without its selects): 10 / 1 000 / 1 tori 52.9 /
  424.5 / 69.3 -> 54.9 / 460.5 / 73.5 ms (a gather at a per-lane offset loses the
  constant displacement of its address);
* speculative traversal (Aila and Laine, "Understanding the Efficiency of Ray Traversal on
  GPUs", 2009): a lane that has a leaf waiting keeps stepping through inner nodes until its
  next reference is a leaf too, so that fewer packet iterations alternate between steps and
  triangle tests: 2^20 rays, in alternation, phase 1, rays aimed at one torus / random
  through 1 / 10 / 1 000 tori 73.8 / 69.2 / 56.5 / 436.7 -> 92.3 / 76.6 / 65.2 / 486.3 ms,
  hits identical (its steps cull with an older nearest distance, so it takes more of them);
* a leaf child scheduled in the step that chooses it (its triangles then tested without the
  step that would have reached the leaf): the same rays, 72.5 / 69.0 / 55.5 / 430.2 ->
  75.4 / 70.5 / 56.7 / 445.3 ms, hits identical;
* a node's 12 box coordinates as six 64-bit gathers of coordinate pairs, split by a shift
  and truncations (half the gathered elements): 2^20 random rays, phase 1, in alternation,
  1 / 10 / 1 000 tori 68.9 / 57.7 / 433.7 -> 70.9 / 56.9 / 439.8 ms, hits identical;
* mesh walks at 32 lanes (Dr.Jit's LLVM width set through its core library): rays aimed at
  one torus 73.9 -> 85.2 ms, random rays through 10 tori 56.8 -> 71.3 ms;
* several rays per lane in a mesh walk, each lane starting its next ray as soon as one ends
  (so that the lanes of a packet stay busy; 2^20 rays, phase 1 of one torus's walk in its
  object space, hits identical): random rays through the torus 54.5 -> 49.2 / 41.4 / 44.3 ms
  at 4 / 16 / 64 rays per lane, but rays aimed at it 89.2 -> 102.7 / 100.2 / 95.7 ms: the
  refill's branch costs every iteration what the busier lanes save on coherent rays;
* one instance-aware BVH for the LEGO scene instead of two levels: an SAH tree over every
  (instance, triangle) pair's world box (2.0 million), each triangle tested in its
  instance's object space as in the two-level walk (hits equal but for coincident faces):
  2^20 random rays 863 -> 572 ms, 2^20 camera rays 385 -> 282 ms, for 4.2 s more build
  (the two-level walk has gained since the baked-tree comparison above, so the flat tree's
  lead is 1.4 - 1.5x, not 2x); once the top level walked in nested loops, the LEGO bricks
  merged into one mesh of 2.0 million triangles (their world coordinates, one BVH, one
  instance) traced 2^20 random rays 752 -> 504 ms and 1 024^2 camera rays 62.4 -> 53.1 ms
  (full record, in alternation) for 2.4 s more load (7.3 -> 9.7 s);
* the rays of the clustered field that meet a frontier box (0.3 %) packed by `dr.compress`
  and walked in a kernel of their own after one that tests the frontier for every ray: the
  packed walks take 1.0 ms, but the frontier kernel (1.6 ms), the compaction (0.5 ms), the
  miss records' fills (1.4 ms) and phase 2 in its own kernel (1.6 ms) cost more than the
  one kernel (5.1 ms): 2^20 random rays 6.3 -> 8.1 ms per full record, hits equal;
* the mesh instances of the LEGO scene re-braided into the top level (each brick entered at
  up to 16 or 128 subtrees of its BVH, each with its world box; phase 1 of 2^20 random rays,
  in alternation): through the grid 1 205 -> 1 178 ms (4 subtrees), 1 202 -> 1 192 ms (16);
  through a top-level BVH 1 198 -> 1 024 ms (16), 1 203 -> 1 007 ms (128), about what the
  top-level BVH alone gains (now `auto`'s choice there);
* the meshes' SAH build over clusters (runs of at most 32 or 8 triangles in Morton order,
  the SAH splitting the clusters, weighted by their sizes, above them and each cluster's
  triangles below; after "HLBVH", Pantaleoni and Luebke 2010): the LEGO scene's 2 million
  triangles in one tree 28.2 -> 10.1 - 11.3 s, but 2^20 random rays traced 1.16 - 1.19x
  slower (481 -> 559 ms, 454 -> 539 ms); with the clusters unweighted, 1.29x slower, and the
  material-preview scene 0.54 -> 0.33 s to load and 1.08x slower to trace;
* the top of the walk's stack kept in a loop variable, so that a pop reads no local memory
  before the next step (the entry below it loaded meanwhile): 2^20 random rays, phase 1,
  in alternation, 1 / 10 / 1 000 tori 69.8 / 54.0 / 433.2 -> 68.5 / 54.1 / 433.2 ms,
  100 000 clustered spheres 8.1 -> 7.9 ms, hits identical;
* again the BVH step without branches, after the slab test became compare-and-select (the
  step's arithmetic then costs less, so the branches weigh more): 10 tori 69.6 -> 78.7 ms
  (8 lanes), 54.8 -> 55.6 ms (4 lanes), 1 000 tori 487.7 -> 564.2 ms, hits identical;
* sorting random rays by direction octant and origin cell (8^3 cells, NumPy argsort, its
  cost not counted) before phase 1 through 10 / 1 000 tori: 63.2 / 497.7 -> 54.8 / 464.4 ms
  at 4 lanes, 81.9 / 552.0 -> 61.5 / 526.3 ms at 8: 1.07 - 1.33x, about what the sort of
  2^20 rays costs (`instancing.accel.ray_order` gathers them in 16 ms);
* phase 1 of mesh scenes at 4 lanes (phase 2 at 16) against both at 8 lanes, then their
  width: on 2^20 random rays through 10 / 1 000 / 10 000 tori 74.2 / 483.4 / 813.3 ->
  57.7 / 448.1 / 725.8 ms (full record), but on camera-like rays (1 024^2 rays of a
  46-degree view, phase 1 alone) 0.91x at 10 and 1 000 tori, 1.08x at 100 000 and 0.74x on
  the forest: the better width depends on how coherent a batch is, and renders (whose rays
  are mostly coherent) were 0.89 - 1.14x at 4 lanes (forest `path` the only gain).

The meshes' SAH build on Dr.Jit (1 million triangles of a noisy sphere, second build in a
process):

* the bins filled in per-thread copies (Dr.Jit's `Expand` mode, arrays padded to a power of
  two) at every level instead of up to 1 024 bins: 2.7 -> 3.3 s, the copies' memsets
  (1.3 s in the first build) outweighing the atomics they save; pre-reducing within a
  packet (`Local`) or plain atomics (`Direct`) above 1 024 bins: 2.5 s either way. (Once
  the nodes of at most 8 items were scored without bins, per-thread copies of up to 2^20
  entries each paid: `accel.sah._EXPAND_ENTRIES` in docs/how-it-works.md.)
* binning 8 192 or 16 384 nodes at a time instead of 32 768 (so that each chunk's bins
  fit the per-thread copies): LEGO load, median of 3, 5.10 / 5.61 and 5.36 / 5.20 s
  against 5.24 / 5.30 s: within noise;
* the triangle areas from their components instead of `np.cross` and `np.linalg.norm`
  (bit-identical; 0.11 -> 0.08 s alone on a million triangles): one PLY of 999 698
  triangles 2.23 / 2.53 / 2.31 -> 2.33 / 2.89 / 2.41 s to load, processes alternating
  (an earlier two pairs: 2.41 / 2.33 -> 2.10 / 2.82 s);
* the allocator tuned for NumPy's large temporaries, whose first touch costs much on this
  virtual machine (a million triangles' areas 0.48 - 0.54 s in fresh memory, 0.11 s in
  reused): NumPy's huge-page advice off 3.33 -> 3.07 s for that PLY, glibc's mmap
  threshold at 32 MiB without trimming 3.45 s, both 3.11 s; LEGO 5.43 / 5.69 -> 5.87 s
  (advice off) and 5.65 s (both).
  Nothing kept: process-wide settings that a library should not change for its users;
* the mesh library's arrays (leaf-order corners, normals, uvs, areas) made for all meshes in
  one pass instead of one mesh after the other: one mesh of 999 698 triangles 3.9 -> 3.5 s
  to load, but the LEGO scene (439 meshes, 2 million triangles) 6.5 -> 8.0 s (the large
  temporaries of the one pass against each mesh's small ones).

The top-level BVH over instances (2^20 random rays, full record, in alternation; ms):

* SAH traversal cost 0.5 or 2 instead of 1 (the meshes' cost): 100 000 clustered spheres
  6.9 / 7.3 against 6.9, 1 000 spheres 118.7 / 139.1 against 119.4, 1 000 tori 347.9 /
  386.2 against 351.2; the forest `path` at 4 spp 158.7 / 160.5 against 160.4.

Mostly-miss rays (the clustered field, phase 1 alone, sequential runs):

* the rays that meet a top-level BVH's frontier packed densely (`dr.compress` after a kernel
  that tests the frontier boxes alone) and walked in full packets, the others missing
  without a walk: 100 000 clustered spheres, 2^20 random rays, phase 1 11.3 -> 15.0 ms. Of
  the 18 294 rays (1.7 %) that meet the frontier, the packed walk alone took 6.6 ms, about
  what the same walks cost one live lane per packet (5.7 ms); the extra kernel's 8 box tests
  (5.1 ms) come on top. On today's code the walks themselves do gain from packing (13 465
  walkers, 2^20 rays, kernel time: 12.1 ms one walker per packet, 5.3 ms packed, 1.75 ms
  with no walker), but the 0.3 % of random rays that walk cost 2.9 ms in the fused kernel,
  about what a second pass over the rays and phase 2 in a kernel of its own cost (the
  few-instance entries below).

Few instances, `scene.intersect` on 2^20 random rays (timed in alternation while another
benchmark ran, so only the ratios count):

* the hits packed densely before phase 2 (`dr.compress`, the float64 record computed for
  them alone and gathered back): 10 rectangles / cylinders / cubes / spheres / disks / tori
  0.96x / 0.86x / 0.92x / 1.00x / 0.81x / 0.99x of the time with phase 2 in a branch that
  packets without a hit skip (it is a quarter to a third of the analytic kinds' time): the
  extra kernels and passes over the rays cost what the packing saves. Again on a quiet
  machine, packing only where at most half the rays hit, images identical, median of 9 in
  alternation: 10 spheres / rectangles / cylinders / cubes / tori 0.75x / 0.68x / 0.78x /
  0.66x / 0.91x of the throughput, 1 000 spheres / rectangles 0.83x / 0.84x, the clustered
  field 0.83x: phase 1 then runs as a kernel of its own instead of fused with phase 2.
  Packed instead by a slot per hit from `dr.scatter_inc` inside phase 1's kernel, the record
  computed for the hits alone and gathered back by slot (10 spheres, 2^20 random rays, 14 %
  hit): phase 1's kernel 7.6 -> 16.3 ms with the slot counter, the gather-back 5.0 ms, the
  packed float64 record itself 1.0 - 1.7 ms; 25.4 ms per full record against 15.8 ms;
* (ray, instance) pairs for the rays that enter each unrolled instance's box, packed and
  tested in one kernel (each torus walk in full packets instead of packets with a few live
  lanes), the nearest per ray by an atomic minimum of (t, instance) keys: 10 tori 1.13x
  faster (0.33 million pairs: building them 59 ms, their walks 100 ms, against 257 ms for
  phase 1 unrolled), 10 cubes / cylinders 0.47x / 0.54x; a dense packet's walk still lasts
  as long as its longest ray's.
* `scene.intersect` on Dr.Jit rays replayed from a `dr.freeze` recording instead of traced
  on every call (tracing the query of 10 rectangles takes 2.2 ms of a 2^20-ray call's 16 -
  19 ms): 2^20 rays 15.85 -> 15.4 - 16.0 ms, 65 536 rays 2.23 -> 1.42 - 2.69 ms (in
  alternation, quiet machine). Walking the scene for the recording's inputs and evaluating
  every field of the hit record cost about what the tracing did.
* phase 2 in a branch per instance for scenes of at most 12 instances (the instance known
  when traced: its rows read and its float64 inverse computed once per packet, its kind's
  test alone): 2^20 random rays, full record, 10 rectangles / cylinders / cubes
  18.5 / 23.6 / 27.8 -> 18.3 / 25.8 / 34.8 ms; ten copies of the float64 record in one
  kernel cost more than the per-lane inverse they save.
* phase 2's float64 inverse read from a per-instance float64 table instead of inverted per
  lane, and its normalisations (the normal, the re-projected sphere and cylinder points) by
  one reciprocal instead of three divisions: 2^20 random rays, full record, 10 spheres /
  cylinders / rectangles / cubes no faster than before (45.7 / 38.6 / 30.8 / 45.4 against
  45.6 / 38.5 / 30.5 / 49.5 ns per ray with the table; 38.7 / 39.1 / 30.7 / 45.8 against
  45.6 / 38.6 / 30.2 / 45.8 with the reciprocals; in alternation while the recovery suite
  ran). Phase 2 with its float64 test replaced by phase 1's distance costs what phase 1
  alone does (sphere 24.1 / 24.6 ns per ray): the time is the float64 test's arithmetic
  (about 130 double operations per 16-lane packet for the sphere), not its divisions,
  branch or stores;
* the sphere's test (both phases) with one reciprocal of the squared direction length in
  place of two of its three divisions (10 of the 33 float32 divisions per 16-lane packet of
  phase 1 at 10 spheres): 2^20 random rays, in alternation on a quiet machine, phase 1
  12.92 -> 12.79 ns per ray at 10 spheres and 94.45 -> 92.54 at 1 000, full record 20.29 ->
  19.83 and 89.40 -> 87.74, hits identical: 1 - 2 %, not worth phase 1's distances moving by
  an ulp against the stress suite's tie cases;
* the top-level BVH instead of the unrolled tests for a few mesh instances: faster on random
  rays (10 tori 13.84 against 12.23 Mrays/s, in alternation) but slower in renders (3 / 6 / 11
  tori over a floor, 256x192, ms: `direct` 16 spp 19.3 / 34.3 / 58.2 unrolled against
  31.0 / 39.4 / 69.1, `path` 4 spp 13.3 / 29.1 / 68.5 against 18.4 / 30.0 / 74.0);
* in the clustered field, after the frontier test, the rays that hit a frontier box packed
  (`dr.compress`) and walked alone: phase 1 on 100 000 clustered spheres 12.1 -> 11.4 ms per
  2^20 rays; the 2 % of rays that enter a cluster take 5.7 ms on their own, and each extra
  kernel costs about 1.4 ms;
* the float64 inverses of the instances' linear parts computed once and gathered per lane in
  phase 2 instead of computed per lane: 10 rectangles / cylinders / cubes 14.2 / 19.7 / 22.1
  -> 14.6 / 19.6 / 22.6 ms per full record of 2^20 rays; gathering twelve doubles per lane
  costs what computing them does;
* the unrolled instances tested without their world-box branch, every lane running every
  instance's test (the idea: with 10 - 20 % of the lanes needing each instance, few packets
  would skip a test, leaving the box test as overhead): 2^20 random rays, full record, median of 7 in
  alternation, 10 spheres / cubes / rectangles / disks / cylinders 48.2 / 46.6 / 69.8 /
  83.4 / 52.3 Mrays/s with the branch, 43.5 / 50.0 / 65.7 / 69.6 / 49.9 without, and
  37.7 / 43.4 / 54.6 / 62.3 / 39.5 with the box test as a lane mask but no branch: the
  packets skip often enough that the branch pays everywhere but the cube;
* packets of 32 lanes instead of 16 for the few-instance scenes (more independent work per
  packet for phase 2's float64 chains): 10 spheres / rectangles / cubes / cylinders 20.9 /
  14.4 / 22.1 / 19.7 -> 21.2 / 15.7 / 22.6 / 21.2 ms per full record of 2^20 rays;
* phase 2's forward rows read as three float4 packets from a 12-float copy per instance
  instead of twelve scalar gathers: 10 spheres / cubes / rectangles / cylinders / disks 24.7 /
  26.7 / 16.4 / 22.5 / 16.4 -> 24.6 / 25.0 / 17.9 / 21.8 / 16.3 ms per full record of 2^20
  rays (median of 9 in alternation, records identical): within noise, for 12 B more per
  instance.

The fall from 1 000 to 100 000 instances:

* loading the next item's instance index one iteration ahead in the grid walk:
  1.81 -> 1.70 and 1.53 -> 1.51 Mrays/s;
* storing the instances in Morton order: 1.56 / 1.58 -> 1.58 / 1.74 (noise);
* several rays per SIMD lane, each lane starting its next ray as soon as one ends: phase 1 at
  100 000 2.69 -> 2.98 Mrays/s with 8 rays per lane, 2.68 with 16; at 1 000 8.08 -> 7.48;
* transparent huge pages for Dr.Jit's buffers (glibc's `hugetlb` tunable): no change;
* each instance's rows padded to one 64-byte cache line (1 000 / 100 000 in alternation:
  6.71 / 1.72, 7.28 / 2.00, 7.25 / 2.23 -> 7.29 / 1.93, 6.91 / 1.93, 6.91 / 2.09): no change,
  and 16 B more per instance;
* 32-lane instead of 16-lane kernels (Dr.Jit's LLVM vector width; 1 000 / 100 000:
  5.19 / 1.44 and 6.89 / 1.85 at 16 lanes, 5.35 / 1.54 and 6.52 / 1.83 at 32; 8 lanes slower);
* sorting the rays inside `scene.intersect` with Dr.Jit's `block_mkperm` by origin cell and
  octant: 1 000 6.80 -> 4.87, 100 000 1.99 -> 2.18. The sort that is kept (by grid entry cell)
  costs a third as much: a counting sort, the rays gathered from an interleaved copy and
  evaluated once, and only in scenes past 6 MiB of walk data.

With the grid walked in one loop, no passes (1 000 / 100 000 in one process, without -> with):

* a mailbox of the last 2 - 6 instances tested (skipping a repeat within the same loop
  iteration): 28 - 29 % fewer instance tests (8.04 -> 5.82 and 14.57 -> 10.29 per ray, same
  hits) and no time saved (6.50 / 1.77 -> 6.20 - 6.50 / 1.57 - 1.82): the loop iterations, not
  the tests, set the time, and a packet runs as many as its slowest lane;
* a second DDA step in the same iteration past an empty cell: 7.15 / 2.28 -> 6.78 / 2.11;
* gathering the next item's instance rows one iteration ahead: 6.97 / 1.98 -> 4.84 / 1.40
  (13 more loop variables spill);
* each cell's first instance stored in the cell table, read with the cell's range:
  6.49 / 1.71 -> 5.85 / 1.57.

With the walk in passes:

* sorting the rays still walking by their cell before each pass (a counting sort over
  4^3-cell blocks with `dr.scatter_inc` and `dr.prefix_sum`): 7.77 / 2.80 and 7.18 / 2.40
  without, 6.71 / 2.30 and 6.52 / 2.49 with.

Loading:

* a bulk JSON reader for scenes of matrices (every instance's plain 4x4 `to_world` cut out of
  the text by one regular expression, its numbers converted by one `np.fromstring` call, the
  rest decoded by `json.loads`; results bit-identical): decoding 100 000 matrices
  1.77 -> 1.30 s, of which 0.48 s the float conversion (about 300 ns per number) and 0.50 s
  the strict number grammar's regular expression. The load stays above 1 s (building the
  scene from the decoded entries takes another 1.0 s in that run), so the extra parser was not
  kept;
* a compiled JSON parser (orjson 3.13) for the same file: 0.86 - 1.11 s against `json.loads`'
  1.18 - 1.82 s in the same runs; making 1.6 million Python floats costs about as much as the
  parse. (Kept later: simdjson, which hands a matrix over without Python floats.)

Participating media (`volpath`, Mitsuba's `test_homo_emitter_inside_medium_volpath.xml`,
64x48, 256 spp, median of 3 renders):

* a scattering event's two shadow rays (environment and lamp) walked one after the other in
  one loop over the surfaces they pass, so that a lane whose first ray ends early goes on
  with its second instead of waiting for the packet's longest walk: 8.78 -> 8.74 s. The
  walks' own cost sets the time, not lanes idle between the two loops;
* the path loop evaluated, one kernel per event with the finished paths compacted away
  (`dr.while_loop(mode="evaluated", compress=True)`, max_depth 6, after the roulette of faint
  shadow rays): the kernels' time 5.11 -> 4.72 s, but a loop that compacts cannot be replayed
  from `render`'s `dr.freeze` recording (Dr.Jit traces it again at every call), and the
  packets' lanes idle in the shadow walks, not between paths.

Queries of a few rays:

* the hit record packed into one Float and one Int32 array inside the recorded kernel (two
  read-backs instead of nine): each `dr.scatter` into the packed arrays became a kernel of
  its own that ran the whole query again (1 000 spheres, 4 096 rays: 0.77 -> 3.35 ms), and
  with the fields evaluated first, eight more kernel launches per query cost more than the
  read-backs saved.

Path replay (gradient steps):

* the previous vertex's own motion in closed form (its hit moving along its detached ray by
  `d (n . v) / (n . d)`, v the motion of its instance's material point; its point and normal
  kept in the loop state) instead of re-intersecting it in each step where instances move:
  gradient images equal to float32 rounding (relative 1e-7), the Cornell box's reverse step
  (256x256, 8 spp, three alternating rounds) 0.78 / 0.81 / 0.84 -> 0.78 / 0.80 / 0.96 s at
  `max_depth` 3 and 1.48 / 1.52 / 1.54 -> 1.53 / 1.56 / 1.51 s at 8, two path-gradient tests
  35.3 / 37.0 -> 39.5 / 35.2 s: the re-intersection is not where the step's time goes."""


# ---------------------------------------------------------------------------
# Sections
# ---------------------------------------------------------------------------

def _uniform_rows(rows: list[dict], kind: str) -> dict[int, dict]:
    return {r["instances"]: r for r in rows if r["kind"] == kind and not r["clustered"]}


def _ratio(a: Any, b: Any) -> float:
    return a / b if is_number(a) and is_number(b) and b != 0 else math.nan


def intersect_section(data: dict) -> list[str]:
    rows = data["rows"]
    rays = max((r.get("mi_full_rays", 0) for r in rows), default=0)
    out = ["## Intersection throughput", "", paragraph(INTERSECT_METHOD)]
    if rays:
        out[-1] += f" Rays per measurement: {count(rays)}."
    out += ["", "Mrays/s; \"prelim\" is Mitsuba's `ray_intersect_preliminary` (Embree), \"full\" its "
            "`ray_intersect`.", ""]
    body = []
    for r in rows:
        body.append([r["kind"], count(r["instances"]), "clustered" if r["clustered"] else "uniform",
                     r["picked"], fixed(r["build_s"]), rate(r["ours"]), rate(r["grid"]), rate(r["bvh"]),
                     rate(r["ours_prelim"]), rate(r["mi_prelim"]), rate(r["mi_full"]),
                     fixed(_ratio(r["ours"], r["mi_prelim"])), fixed(_ratio(r["ours_prelim"], r["mi_prelim"])),
                     sig(_ratio(r["ours"], r["mi_full"])), f"{100 * r['hit_fraction']:.0f}"])
    out.append(table(["kind", "instances", "layout", "structure", "build s", "ours", "grid", "BVH",
                      "ours t+ids", "prelim", "full", "ours / prelim", "t+ids / prelim", "ours / full",
                      "rays that hit %"], body, "llllrrrrrrrrrrr"))
    out.append("")

    kinds = list(dict.fromkeys(r["kind"] for r in rows))
    spheres = _uniform_rows(rows, "sphere")
    targets = []
    if 1000 in spheres:
        s = spheres[1000]
        prelim, full = _ratio(s["ours"], s["mi_prelim"]), _ratio(s["ours"], s["mi_full"])
        targets.append(f"1 000 spheres, full hit record against Embree's preliminary one: {times(prelim)} "
                       f"(target >= {TARGET_PRELIM_RATIO:g}x: {verdict(prelim >= TARGET_PRELIM_RATIO)}).")
        if is_number(full):
            targets.append(f"1 000 spheres against Mitsuba's full `ray_intersect`: {sig(full)}x "
                           f"(target >= {TARGET_FULL_RATIO:g}x: {verdict(full >= TARGET_FULL_RATIO)}).")
    fall = data.get("fall_sphere")
    alternating = data.get("fall_sphere_alternating")
    if is_number(fall):
        text = f"1 000 -> 100 000 spheres: throughput falls {times(fall)} between the rows"
        if is_number(alternating):
            text += f", {times(alternating)} timed in alternation"
        worst = max(v for v in (fall, alternating) if is_number(v))
        targets.append(text + f" (target < {TARGET_FALL:g}x: {verdict(worst < TARGET_FALL)}); "
                       "the other kinds are in the table below.")
    builds = [r["build_s"] for r in rows if r["instances"] == 100000]
    if builds:
        targets.append(f"Build of 100 000 instances: {span(builds, fixed)} s "
                       f"(target < {TARGET_BUILD_S:g} s: {verdict(max(builds) < TARGET_BUILD_S)}).")
    out += ["Targets:", ""] + [f"* {t}" for t in targets] + [""]

    fall_rows = []
    for kind in kinds:
        by_n = _uniform_rows(rows, kind)
        if 1000 not in by_n or 100000 not in by_n:
            continue
        ours_fall = data.get(f"fall_{kind}", _ratio(by_n[1000]["ours"], by_n[100000]["ours"]))
        embree_fall = _ratio(by_n[1000]["mi_prelim"], by_n[100000]["mi_prelim"])
        hits = f"{100 * by_n[1000]['hit_fraction']:.0f} -> {100 * by_n[100000]['hit_fraction']:.0f}"
        gain = data.get(f"sort_gain_{kind}")
        fall_rows.append([kind, rate(by_n[1000]["ours"]), rate(by_n[100000]["ours"]), times(ours_fall),
                          verdict(ours_fall < TARGET_FALL) if is_number(ours_fall) else "-",
                          times(embree_fall), hits, times(gain)])
    if fall_rows:
        out += ["From 1 000 to 100 000 instances, per kind (\"sort gain\": phase 1 at 100 000 instances "
                "with the rays sorted by grid entry cell against unsorted, timed in alternation):", ""]
        out.append(table(["kind", "1 000 Mrays/s", "100 000 Mrays/s", "fall", "< 3x", "Embree's fall",
                          "rays that hit %", "sort gain"], fall_rows, "lrrrlrrr"))
        out.append("")

    losses = [r for r in rows if is_number(r["mi_prelim"]) and r["ours"] < r["mi_prelim"]]
    if losses:
        parts = [f"{r['kind']} ({count(r['instances'])} instances{', clustered' if r['clustered'] else ''}) "
                 f"{times(_ratio(r['ours'], r['mi_prelim']))} (t+ids {times(_ratio(r['ours_prelim'], r['mi_prelim']))})"
                 for r in losses]
        out += ["Below Embree's preliminary rate (full record; in brackets, our first phase alone): "
                + "; ".join(parts) + ".", ""]
    return out + _small_batches(data.get("small_batches", []))


def _small_batches(rows: list[dict]) -> list[str]:
    """The fixed cost of a query of a few rays (:func:`benchmarks.intersect.small_batches`)."""
    if not rows:
        return []
    body = [[r["kind"], count(r["instances"]), count(r["rays"]), fixed(r["ours_ms"], 3),
             fixed(r["traced_ms"], 3), fixed(r["mi_prelim_ms"], 3),
             times(_ratio(r["mi_prelim_ms"], r["ours_ms"]))]
            for r in rows]
    slower = [_ratio(r["mi_prelim_ms"], r["ours_ms"]) for r in rows if r["rays"] <= 16]
    out = ["### Queries of a few rays", "",
           paragraph("Milliseconds per `scene.intersect` call on NumPy rays, NumPy hits back (t, p, n, "
                     "instance, prim), against Mitsuba's `ray_intersect_preliminary` on rays built from "
                     "the same NumPy arrays (t and primitive index read back), timed in alternation. "
                     "Our NumPy queries replay a recording of their kernels per batch width; \"traced\" "
                     "is our Dr.Jit record of the same rays, traced every call. \"ours / prelim\" is "
                     "Mitsuba's time over ours."), "",
           table(["kind", "instances", "rays", "ours ms", "traced ms", "prelim ms", "ours / prelim"],
                 body, "lrrrrrr"), ""]
    if slower:
        out += [paragraph(f"At 16 rays or fewer a query takes {span([1 / x for x in slower], times)} "
                          "Mitsuba's time: converting the arrays, handing the scene's arrays to the "
                          "replay and reading the record back cost more than the walk."), ""]
    return out


def _rising_errors(rows: list[dict]) -> list[str]:
    """Per row whose error curve (either renderer's) rises by more than 10 % from one spp to the
    next: "scene `integrator` (ours at spp, ...; Mitsuba's at spp, ...)"."""
    found = []
    for r in rows:
        parts = []
        for who, name in (("ours", "ours"), ("mitsuba", "Mitsuba's")):
            curve = r["curves"][who]
            error, spp = curve["error"], curve["spp"]
            rises = [str(spp[k + 1]) for k in range(len(error) - 1) if error[k + 1] > 1.1 * error[k]]
            if rises:
                parts.append(f"{name} at {', '.join(rises)} spp")
        if parts:
            found.append(f"{r['scene']} `{r['integrator']}` ({'; '.join(parts)})")
    return found


def _render_target(rows: list[dict], key: str, name: str) -> str:
    """The render target's verdict by one estimator of the equal-error speed-up."""
    speedups = sorted((r[key], r["scene"], r["integrator"]) for r in rows if is_number(r[key]))
    unmeasured = [r for r in rows if not is_number(r[key])]
    met = len(speedups) == len(rows) and all(s >= 1 for s, _, _ in speedups)
    smallest = ", ".join(f"{s:.2f}x ({scene} `{integ}`)" for s, scene, integ in speedups[:3])
    text = (f"Target by the {name}: {sum(s >= 1 for s, _, _ in speedups)} of {len(rows)} cases at or "
            f"above 1x, the smallest margins {smallest}; geometric mean "
            f"{geometric_mean(s for s, _, _ in speedups):.2f}: {verdict(met)}.")
    if unmeasured:
        text += " Not reached: " + ", ".join(f"{r['scene']} `{r['integrator']}`" for r in unmeasured) + "."
    return text


def _render_table(rows: list[dict]) -> str:
    """The equal-error table: per scene and integrator, the target, both times at it, the
    speed-ups by both estimators and the error floors."""
    body = []
    for r in rows:
        body.append([r["scene"], r["integrator"], r["mitsuba_mode"],
                     f"{r['target_error']:.4f} @ {r['target_spp']} spp", fixed(r["ours_time_at_target"], 3),
                     fixed(r["mitsuba_time_at_target"], 3), fixed(r["speedup_equal_error"]),
                     fixed(r["speedup_variance_model"]),
                     f"{r['floor_ours']:.4f} @ {r['floor_spp_ours']}",
                     f"{r['floor_mitsuba']:.4f} @ {r['floor_spp_mitsuba']}",
                     f"{r['reference_noise']:.4f}"])
    return table(["scene", "integrator", "Mitsuba's scene", "target error", "ours s", "Mitsuba s",
                  "speed-up at equal error", "variance model", "error floor ours",
                  "error floor Mitsuba", "reference noise"], body, "lllrrrrrrrr")


def _render_targets(rows: list[dict]) -> list[str]:
    return [_render_target(rows, "speedup_equal_error", "first crossing"), "",
            _render_target(rows, "speedup_variance_model", "variance model"), ""]


def render_variant_section(data: dict) -> list[str]:
    """The equal-error table again, every scene rendered with one reconstruction filter
    (``--rfilter``) or one sampler type (``--sampler``)."""
    args, rows = data["args"], data["rows"]
    pairs = sorted({(r["scene"], r["integrator"]) for r in rows})
    chosen = "".join(f" --{key} {' '.join(args[key])}" for key in ("scenes", "integrators") if args[key])
    if args.get("sampler"):
        option, path = f"--sampler {args['sampler']}", RENDER_SAMPLER
        title, what = f"### With Mitsuba's `{args['sampler']}` sampler", (
            f"The bundled scenes draw independent samples, as Mitsuba does by default. The same "
            f"measurement with both renderers' samples stratified over each pixel's samples "
            f"(Mitsuba's `{args['sampler']}` sampler; ours its Owen-scrambled Sobol samples), on "
            f"{len(pairs)} scene/integrator pairs")
        after = (" The variance model assumes the error falls as one over the square root of the "
                 "samples, which stratified samples beat: the first crossing is the figure here.")
    else:
        option, path = f"--rfilter {args['rfilter']}", RENDER_FILTER
        title, what = "### With Mitsuba's default filter", (
            f"The bundled scenes have box filters, while a Mitsuba scene without an `rfilter` gets a "
            f"Gaussian. The same measurement with every camera's filter replaced by Mitsuba's "
            f"`{args['rfilter']}` at its default size, on {len(pairs)} scene/integrator pairs")
        after = " Both renderers splat each sample into the pixels the filter reaches."
    out = [title, "", paragraph(
        f"{what}, {args['width']}x{args['height']} (`python -m benchmarks.render_error {option}{chosen} "
        f"--json {_relative(path)}`).{after}"), "", _render_table(rows), ""]
    return out + _render_targets(rows)


PUBLIC_METHOD = (
    "Mitsuba's own example scenes, which users arrive with: its data repository's documentation "
    "scenes and its tutorials' scenes, on local checkouts (they are not bundled: neither "
    "repository's licence lets this project copy them). `python -m benchmarks.public_scenes "
    "FOLDER --json FILE` loads every XML file unmodified into both renderers and renders each "
    "that both load with the file's own integrator (its `max_depth`, Russian roulette and "
    "`hide_emitters`) at a reduced film size, both renderers in turns, after a warm-up render "
    "each; it compares both against a high-spp Mitsuba reference of the file by the 8x8-block "
    "error, the root mean square over several renders of each. A file matches where our error "
    "is within 1.5x Mitsuba's. Our time at equal error is our time per render over Mitsuba's "
    "times the ratio of the two renderers' noise (an unbiased renderer's variance falls as one "
    "over the samples), on matching files only. The noise is the variance of a pixel's value, "
    "the mean over the pixels of each pixel's own samples' spread, from one more render of each "
    "with Mitsuba's `moment` channels: the block errors of a few renders are no measure of it, "
    "since a few pixels (a light's edge, a highlight) make most of a small image's error (on "
    "Mitsuba's `integrator_depth_1.xml`, a Cornell box, three sets of four renders of each put the "
    "ratio of the block errors at 1.80x, 1.10x and 1.04x, where the noise of both is the same). "
    "At this film size a "
    "render's fixed costs (tracing, compiling, launching kernels) weigh more than in full-size "
    "frames.")


def _group(path: str) -> str:
    """A public scene's group: its file name up to the first underscore ('bsdf', 'emitter'),
    the folder's name for files called scene.xml."""
    parts = path.split("/")
    stem = parts[-1].rsplit(".", 1)[0]
    if stem == "scene" and len(parts) > 1:
        stem = parts[-2]
    return stem.split("_", 1)[0]


def _refusal(detail: str) -> str:
    """The first refused element's reason in a refusal's detail, without the list of
    what is supported."""
    reason = detail.rsplit('">: ', 1)[-1] if '">: ' in detail else detail
    return reason.split("; ", 1)[0].split(" supported:", 1)[0]


def public_matches(runs: Sequence[dict]) -> list[float]:
    """Our time at equal error over Mitsuba's of every matching file of the runs."""
    return [f["equal_error"] for run in runs for f in run["files"]
            if f["verdict"] == "match" and is_number(f.get("equal_error"))]


def _public_row(name: str, matches: list[dict]) -> list[str]:
    """A row of the public-scenes table: a group's matching files, their time per render and
    at equal error against Mitsuba's (over the files with a noise measure)."""
    equal = [m["equal_error"] for m in matches if is_number(m.get("equal_error"))]
    at_equal_error = ([times(geometric_mean(equal)), span(equal, times), str(sum(e < 1 for e in equal))]
                      if equal else ["-", "-", "-"])
    return [name, str(len(matches)), times(geometric_mean(m["ours_s"] / m["mitsuba_s"] for m in matches)),
            *at_equal_error]


def public_section(runs: Sequence[dict]) -> list[str]:
    """Mitsuba's example scenes: verdicts, and render time at equal error by group of files."""
    out = ["### Mitsuba's example scenes", "", paragraph(PUBLIC_METHOD), ""]
    for run in runs:
        settings, files = run["settings"], run["files"]
        verdicts: dict[str, int] = {}
        for f in files:
            verdicts[f["verdict"]] = verdicts.get(f["verdict"], 0) + 1
        out += [paragraph(
            f"{', '.join(f'`{folder}`' for folder in settings['folders'])}: {len(files)} files, "
            f"{settings['size'][0]}x{settings['size'][1]} at {settings['spp']} spp, reference at "
            f"{settings['reference_spp']} spp, {settings['repeats']} renders of each; "
            + ", ".join(f"{verdict} {n}" for verdict, n in sorted(verdicts.items())) + "."), ""]
        groups: dict[str, list[dict]] = {}
        for f in sorted(files, key=lambda f: _group(f["file"])):
            if f["verdict"] == "match":
                groups.setdefault(_group(f["file"]), []).append(f)
        groups["all"] = [f for members in groups.values() for f in members]
        body = [_public_row(name, members) for name, members in groups.items()]
        out += [table(["files", "matching", "time per render, ours / Mitsuba's (geo. mean)",
                       "time at equal error (geo. mean)", "range", "ours faster"], body), ""]
        misses = [f for f in files if f["verdict"] == "MISS"]
        refused = [f for f in files if f["verdict"] == "refused"]
        if misses:
            out += ["Not matching: " + "; ".join(
                f"`{f['file'].rsplit('/', 1)[-1]}` ({times(_ratio(f['ours_error'], f['mitsuba_error']))} "
                f"Mitsuba's error{_known_bias(f['detail'])})" for f in misses) + ".", ""]
        if refused:
            out += ["Refused by ours alone: " + "; ".join(
                f"`{f['file'].rsplit('/', 1)[-1]}` ({_refusal(f['detail'])})" for f in refused) + ".", ""]
    return out


def _known_bias(detail: str) -> str:
    """The note that public_scenes adds to a MISS whose reference Mitsuba renders biased
    ('; Mitsuba 3.9.1's ...'), or ''."""
    start = detail.find("; Mitsuba 3.9.1's")
    return "" if start < 0 else detail[start:]


def render_section(data: dict) -> list[str]:
    args, rows = data["args"], data["rows"]
    out = ["## Render time against error", "", paragraph(RENDER_METHOD)]
    out[-1] += (f" In this run: {args['width']}x{args['height']}, spp up to {args['max_spp']}, target "
                f"at {args['target_spp']} spp, reference at {args['reference_spp']} spp, median of "
                f"{args['repeats']} renders, a renderer stops at the first spp whose median render "
                f"exceeds {args['max_render_s']:g} s.")
    out += ["", _render_table(rows), "", "![render time against error](render_error.png)", ""]
    out += _render_targets(rows)
    rising = _rising_errors(rows)
    if rising:
        out += ["Error curves that rise by more than 10 % from one spp to the next, where a few bright "
                "pixels (fireflies) dominate the relative RMSE, so that the first crossing is not a "
                "reliable speed-up: " + "; ".join(rising) + ".", ""]

    capped = [r for r in rows if r["floor_spp_mitsuba"] < args["max_spp"]]
    if capped:
        parts = [f"{r['scene']} `{r['integrator']}` after {r['floor_spp_mitsuba']} spp (host-side time per "
                 f"render {fixed(r['profile']['mitsuba']['host_s'])} s against our "
                 f"{fixed(r['profile']['ours']['host_s'], 3)} s)" for r in capped]
        out += [paragraph(
            "Mitsuba reached the time cap on " + "; ".join(parts) + ". Those rows compare at Mitsuba's "
            "error there, and their large speed-ups are mostly Mitsuba's fixed host-side cost per render "
            "(building its scene of plain shapes), not traversal."), ""]

    out += [paragraph(RENDER_ESTIMATORS), ""]
    body = []
    for r in rows:
        ours, theirs = r["curves"]["ours"], r["curves"]["mitsuba"]
        spp = r["target_spp"]
        if spp in ours["spp"] and spp in theirs["spp"]:
            t_ours, t_theirs = ours["time_s"][ours["spp"].index(spp)], theirs["time_s"][theirs["spp"].index(spp)]
        else:
            t_ours = t_theirs = math.nan
        body.append([r["scene"], r["integrator"], str(spp), fixed(t_ours, 3), fixed(t_theirs, 3),
                     fixed(_ratio(t_ours, t_theirs)), fixed(ours["error"][0], 3), fixed(theirs["error"][0], 3)])
    out.append(table(["scene", "integrator", "spp", "ours s", "Mitsuba s", "ours / Mitsuba (time per render)",
                      "error at 1 spp, ours", "error at 1 spp, Mitsuba"], body, "llrrrrrr"))
    out.append("")

    body = []
    for r in rows:
        p = r["profile"]
        body.append([r["scene"], r["integrator"]]
                    + [x for who in ("ours", "mitsuba") for x in
                       (str(p[who]["kernels"]), str(p[who]["misses"]), fixed(p[who]["compile_s"], 3),
                        fixed(p[who]["execute_s"], 3), fixed(p[who]["host_s"], 3))])
    out += ["Where the time goes, one more render per renderer at the target spp with Dr.Jit's kernel "
            "history on (kernels launched, of those compiled, compile, execution and host seconds; host: "
            "tracing, launches, copies):", ""]
    out.append(table(["scene", "integrator", "ours kernels", "compiled", "compile s", "execute s", "host s",
                      "Mitsuba kernels", "compiled", "compile s", "execute s", "host s"], body,
                     "llrrrrrrrrrr"))
    out.append("")
    return out


def _later_compiles(counts: Sequence[int]) -> str:
    """Kernels compiled per step: '80, 9, then 0'."""
    counts = list(counts)
    last = max((i for i, c in enumerate(counts) if c), default=-1)
    head = ", ".join(str(c) for c in counts[:last + 1])
    if last + 1 < len(counts):
        return f"{head}, then {counts[last + 1]}" if head else str(counts[0])
    return head


LOADING_METHOD = (
    "`python -m benchmarks --parts loading` (`benchmarks/loading.py`): `load_scene` (parse and "
    "build) of the uniform sphere field given as one 4x4 matrix per instance: in a Python dict, "
    "in the same dict as a list of operations each (`ops`: translate, rotate, scale), in a JSON file, as one entry naming an `.npy` file of the matrices, and as Mitsuba XML (one "
    "`shapegroup`, one `instance` with a `<matrix>` each), beside Mitsuba's `load_file` of the "
    "same XML; medians of {repeats} loads per form, ours and Mitsuba alternating. Targets: under "
    "1 s for a dict or JSON scene of 100 000 instances and for XML with 10 000. How: entries of "
    "at most an id, a model, a material and one transform are read field by field over the whole "
    "list and their matrices checked and inverted as one batch (operation lists: one batch per "
    "sequence of operations, built and composed in NumPy); instances without ids are "
    "stored as runs, not a name each; a JSON file is parsed by simdjson, each such entry's "
    "matrix handed over as float64 values (no Python float per number); and the cyclic "
    "garbage collector pauses while a scene is read (each pass would walk every live object).")


LOADING_MESH_METHOD = (
    "One mesh: a binary PLY heightfield (the terrain scene's hills) loaded as a scene of one "
    "shape by both renderers, reading the file and building the acceleration (our SAH BVH, "
    "built one level of the tree at a time in Dr.Jit kernels; Mitsuba's Embree scene), "
    "alternating; medians.")


def loading_section(data: dict) -> list[str]:
    from benchmarks.loading import TARGETS
    out = ["### Loading at scale", "", paragraph(LOADING_METHOD.format(repeats=data["repeats"])), ""]
    body = []
    for r in data["rows"]:
        target = TARGETS.get(r["form"])
        verdict = "-"
        if target is not None and r["instances"] == target[0]:
            verdict = f"< {target[1]:g} s: " + ("met" if r["ours"] < target[1] else "**missed**")
        body.append([r["form"], count(r["instances"]), fixed(r["ours"]),
                     "-" if r["mitsuba"] is None else fixed(r["mitsuba"]), verdict])
    out += [table(["form", "instances", "ours (s)", "Mitsuba (s)", "target"], body, "lrrrl"), ""]
    if data.get("meshes"):
        out += [paragraph(LOADING_MESH_METHOD), ""]
        body = [[count(r["triangles"]), fixed(r["ours"]), fixed(r["mitsuba"]), times(r["ours"] / r["mitsuba"])]
                for r in data["meshes"]]
        out += [table(["triangles", "ours (s)", "Mitsuba (s)", "ours / Mitsuba"], body, "rrrr"), ""]
    return out


def scale_section(data: dict) -> list[str]:
    rows = data["rows"]
    target = data.get("target_bytes_per_instance")
    out = ["## Scaling, memory and first frames", "", paragraph(SCALE_METHOD)]
    if rows:
        out[-1] += (f" Film {rows[0]['size']}x{rows[0]['size']} at {rows[0]['spp']} spp; later frames are "
                    f"the median of {data.get('repeats', '?')} renders.")
    out.append("")

    def growth(r: dict) -> int:
        return r["rss"]["rendered"] - r["rss"]["base"]

    body = []
    previous = None
    for r in rows:
        slope = (f"{(growth(r) - growth(previous)) / (r['instances'] - previous['instances']):.0f}"
                 if previous else "-")
        held = sum(h["per_instance"] for h in r["held"])
        warm = r.get("warm", {}).get("render_first_s")
        body.append([count(r["instances"]), r["accel"], fixed(r["parse_s"]), fixed(r["build_s"]),
                     f"{fixed(r['render_first_s'])} / {fixed(warm)}", fixed(r["render_later_s"], 3),
                     str(r["render_later_new"]), percent(r["lit_fraction"], 0),
                     f"{fixed(r['step_first_s'])} / {fixed(r['step_later_s'], 3)}",
                     _later_compiles(r["step_new"]), slope, f"{held:.1f}"])
        previous = r
    out.append(table(["instances", "structure", "parse s", "build s", "first image s (cold / warm cache)",
                      "later frames s", "kernels compiled per later frame", "pixels lit",
                      "first / later optimisation step s", "kernels compiled per step",
                      "RSS growth slope B/instance", "held B/instance"],
                     body, "llrrrrrrrrrr"))
    out.append("")

    if rows:
        largest = rows[-1]
        items = sorted((h for h in largest["held"] if h["per_instance"] >= 0.5),
                       key=lambda h: -h["per_instance"])
        rest = sum(h["per_instance"] for h in largest["held"]) - sum(h["per_instance"] for h in items)
        body = [[f"`{h['path']}`", _array_kind(h["kind"]), f"{h['per_instance']:.1f}"] for h in items]
        body.append(["everything else", "", f"{rest:.2f}"])
        out += [f"What the scene holds per instance at {count(largest['instances'])} instances:", ""]
        out.append(table(["attribute", "array", "B/instance"], body, "llr"))
        out.append("")

    targets = []
    by_n = {r["instances"]: r for r in rows}
    if 100000 in by_n:
        load = by_n[100000]["load_s"]
        targets.append(f"100 000 instances load and build in {fixed(load)} s "
                       f"(target < {TARGET_BUILD_S:g} s: {verdict(load < TARGET_BUILD_S)}).")
    if rows:
        largest = rows[-1]
        lit = largest["lit_fraction"]
        targets.append(f"{count(largest['instances'])} instances load in {fixed(largest['load_s'], 1)} s and "
                       f"render (first image {fixed(largest['render_first_s'])} s, {percent(lit, 0)} of the "
                       f"pixels lit): {verdict(is_number(lit) and lit > 0)}.")
        if is_number(target):
            held = sum(h["per_instance"] for h in largest["held"])
            peak = (largest["rss"]["peak"] - largest["rss"]["base"]) / largest["instances"]
            targets.append(f"At most {target:g} bytes per instance: {held:.1f} held at "
                           f"{count(largest['instances'])} instances ({body_slope(rows)}): "
                           f"{verdict(held <= target)}. The peak while loading is higher, {peak:.0f} "
                           f"B/instance of resident-set growth (float64 build temporaries); the slopes "
                           f"below 100 000 instances are the allocator's granularity, not the scene.")
        outside = [(r["instances"], r["render_later_s"] - r["render_later_kernel_ms"] / 1000,
                    r["step_later_s"] - r["step_later_kernel_ms"] / 1000) for r in rows
                   if is_number(r.get("render_later_kernel_ms")) and is_number(r.get("step_later_kernel_ms"))]
        if outside:
            frames = ", ".join(f"{count(n)}: {1000 * f:.1f} ms" for n, f, _ in outside)
            steps = ", ".join(f"{count(n)}: {1000 * s:.0f} ms" for n, _, s in outside)
            targets.append(f"Time outside kernels per later frame ({frames}) and per later optimisation step "
                           f"({steps}); what remains in a step is host work on the moved instances "
                           f"(value checks, re-filing their grid references, their silhouette curves, "
                           f"the search for their shadow casters and contacts among all instances).")
    out += ["Targets and remarks:", ""] + [f"* {t}" for t in targets] + [""]

    freeze = data.get("freeze", [])
    if freeze:
        body = [[str(f["spp"]), fixed(1000 * f["plain_s"], 1), fixed(1000 * f["frozen_s"], 1),
                 fixed(1000 * f["plain_kernel_s"], 1), fixed(1000 * f["frozen_kernel_s"], 1),
                 str(f["recordings"]), "yes" if f["identical"] else "**no**"] for f in freeze]
        out += ["Traced (`frozen=False`) against replayed renders, 1 000 instances at 64x64, in separate "
                "small processes (ms per frame):", ""]
        out.append(table(["spp", "traced ms", "replayed ms", "traced kernels ms", "replayed kernels ms",
                          "recordings", "images identical"], body, "rrrrrrl"))
        out.append("")
    return out


def _array_kind(kind: str) -> str:
    """'drjit Float x12000000' -> 'drjit Float, 12 000 000 entries'."""
    match = re.fullmatch(r"(.*) x(\d+)", kind)
    return f"{match.group(1)}, {count(int(match.group(2)))} entries" if match else kind


def body_slope(rows: list[dict]) -> str:
    """'124 B/instance resident-set slope from 100 000' for the last two rows."""
    if len(rows) < 2:
        return "no slope"
    a, b = rows[-2], rows[-1]
    ga = a["rss"]["rendered"] - a["rss"]["base"]
    gb = b["rss"]["rendered"] - b["rss"]["base"]
    return (f"{(gb - ga) / (b['instances'] - a['instances']):.0f} B/instance resident-set slope from "
            f"{count(a['instances'])}")


def gradient_section(data: dict) -> list[str]:
    out = ["## Differentiable rendering", ""]
    labels = {"sphere": "sphere (rotated, scaled)", "cube": "cube (rotated, sheared)",
              "rectangle": "rectangle (rotated, scaled)", "disk": "disk (rotated, reflected)",
              "cylinder": "cylinder (rotated, scaled)", "mesh": "torus mesh (rotated, reflected)"}

    def grid(entries: list) -> tuple[list[list[str]], list[float]]:
        models = list(dict.fromkeys(e[0] for e in entries))
        params = list(dict.fromkeys(e[1] for e in entries))
        value = {(e[0], e[1]): e[2] for e in entries}
        body = [[labels.get(m, m)] + [percent(value.get((m, p))) for p in params] for m in models]
        return [["model (transform)"] + params] + body, [e[2] for e in entries]

    if data.get("validation"):
        (header, *body), errors = grid(data["validation"])
        within = sum(e <= TARGET_GRADIENT_ERROR for e in errors if is_number(e))
        out += ["### Gradient accuracy", "", paragraph(GRADIENT_METHOD), ""]
        out += [table(header, body), ""]
        out += [f"{within} of {len(errors)} within the {percent(TARGET_GRADIENT_ERROR, 0)} target "
                f"(largest {percent(max(errors))}).", ""]
    for entry, title, text in (("shadow", "With shadows in view", GRADIENT_SHADOW),
                               ("shadow_path", "With shadows in view, `path`", GRADIENT_SHADOW_PATH)):
        if not data.get(entry):
            continue
        (header, *body), errors = grid(data[entry])
        out += [f"### {title}", "", paragraph(text), ""]
        out += [table(header, body), ""]
        rows = [e for e in data[entry] if len(e) >= 5 and is_number(e[3])]
        if rows:
            met = sum(e[2] <= min(1.5 * e[3], TARGET_GRADIENT_ERROR) for e in rows)
            out += [f"{met} of {len(rows)} within the target; the finite differences' spread "
                    f"{span([e[3] for e in rows], percent)}; without the shadow terms the errors "
                    f"are {span([e[4] for e in rows if is_number(e[4])], percent)}.", ""]
        else:
            out += [f"Errors {span(errors, percent)}, measured before the shadow term existed.", ""]
    for entry, title, text in (("mitsuba", "Against Mitsuba with shadows in view", GRADIENT_MITSUBA),
                               ("mitsuba_area", "Against Mitsuba with soft shadows",
                                GRADIENT_MITSUBA_AREA),
                               ("mitsuba_area_path", "Against Mitsuba's `prb_projective`",
                                GRADIENT_MITSUBA_AREA_PATH)):
        if data.get(entry):
            out += _mitsuba_comparison(data[entry], title, text)
    if data.get("penumbra"):
        rows = data["penumbra"]
        met = sum(e[4] <= min(1.5 * e[5], TARGET_GRADIENT_ERROR) for e in rows)
        out += ["### Soft shadows and interreflection", "", paragraph(GRADIENT_PENUMBRA), "",
                table(["model", "parameter", "light", "integrator", "error", "FD spread", "without"],
                      [[labels.get(e[0], e[0]), e[1], e[2], e[3], percent(e[4], 2), percent(e[5], 2),
                        percent(e[6], 2)] for e in rows], "llllrrr"), ""]
        out += [f"{met} of {len(rows)} within the target; without the term the errors are "
                f"{span([e[6] for e in rows], percent)}.", ""]
    if data.get("interreflection"):
        rows = data["interreflection"]
        met = sum(e[1] <= min(1.5 * e[2], TARGET_GRADIENT_ERROR) for e in rows)
        out += [paragraph(GRADIENT_INTERREFLECTION), "",
                table(["model", "error", "FD spread", "without"],
                      [[labels.get(e[0], e[0]), percent(e[1], 2), percent(e[2], 2), percent(e[3], 2)]
                       for e in rows], "lrrr"), ""]
        out += [f"{met} of {len(rows)} within the target.", ""]
    if data.get("reflected"):
        rows = data["reflected"]
        met = sum(e[4] <= min(1.5 * e[5], TARGET_GRADIENT_ERROR) for e in rows)
        out += [paragraph(GRADIENT_REFLECTED.format(size=rows[0][3])), "",
                table(["model", "light", "max_depth", "error", "FD spread", "without", "seconds"],
                      [[labels.get(e[0], e[0]), e[1], str(e[2]), percent(e[4], 2), percent(e[5], 2),
                        percent(e[6], 2), f"{e[7]:.0f}"] for e in rows], "llrrrrr"), ""]
        out += [f"{met} of {len(rows)} within the target.", ""]
    if data.get("contact"):
        rows = data["contact"]
        params = list(dict.fromkeys(e[1] for e in rows))
        value = {(e[0], e[1]): e[2] for e in rows}
        body = [[m] + [percent(value.get((m, p))) for p in params]
                for m in dict.fromkeys(e[0] for e in rows)]
        met = sum(e[2] <= min(1.5 * e[3], TARGET_GRADIENT_ERROR) for e in rows)
        out += ["### Contact curves", "", paragraph(GRADIENT_CONTACT), "",
                table(["model"] + params, body), ""]
        out += [f"{met} of {len(rows)} within the target; the finite differences' spread "
                f"{span([e[3] for e in rows], percent)}; without the contact term the errors are "
                f"{span([e[4] for e in rows], percent)}.", ""]
    if data.get("touching"):
        rows = data["touching"]
        met = sum(e[2] <= min(1.5 * ((e[3] ** 2 + e[4] ** 2) / 2) ** 0.5, TARGET_GRADIENT_ERROR)
                  for e in rows)
        out += ["### Touching instances", "", paragraph(GRADIENT_TOUCHING), "",
                table(["model", "parameter", "error", "our spread", "FD spread", "without"],
                      [[e[0], e[1], percent(e[2], 2), percent(e[3], 2), percent(e[4], 2), percent(e[5], 2)]
                       for e in rows], "llrrrr"), ""]
        out += [f"{met} of {len(rows)} within the target.", ""]
    if data.get("delta"):
        rows = data["delta"]
        met = sum(e[3] <= min(1.5 * ((e[4] ** 2 + e[5] ** 2) / 2) ** 0.5, TARGET_GRADIENT_ERROR) for e in rows)
        out += ["### Moving mirrors and glass", "", paragraph(GRADIENT_DELTA), "",
                table(["case", "parameter", "max_depth", "error", "our spread", "FD spread"],
                      [[e[0], e[1], str(e[2]), percent(e[3], 2), percent(e[4], 2), percent(e[5], 2)]
                       for e in rows], "llrrrr"), ""]
        out += [f"{met} of {len(rows)} within the target.", ""]
    if data.get("lights"):
        rows = data["lights"]
        met = sum(e <= min(1.5 * s, TARGET_GRADIENT_ERROR) for _, e, s in rows)
        out += ["### Moving lamps", "", paragraph(GRADIENT_LIGHTS), ""]
        out += [table(["lamp parameter", "error", "finite differences' spread"],
                      [[label, percent(e), percent(s)] for label, e, s in rows], "lrr"), ""]
        out += [f"{met} of {len(rows)} within the target.", ""]
    if data.get("depth"):
        rows = data["depth"]
        size, spp = rows[0]["size"], rows[0]["spp"]
        out += ["### Memory against path depth", "", paragraph(GRADIENT_DEPTH.format(size=size, spp=spp)), ""]
        out += [table(["method", "max_depth", "s / step", "peak MB"],
                      [[r.get("method", "evaluated loop"), str(r["max_depth"]), fixed(r.get("seconds"), 3),
                        f"{r.get('peak_mb', float('nan')):.0f}"] for r in rows], "lrrr"), ""]
    if data.get("cost"):
        body = []
        ratios = []
        for c in data["cost"]:
            ours, theirs = c["ours"], c["mitsuba"]
            if is_number(theirs.get("seconds")):
                ratio = theirs["seconds"] / ours["seconds"]
                ratios.append(ratio)
                theirs_s, theirs_mb, ratio_s = fixed(theirs["seconds"], 3), f"{theirs['peak_mb']:.0f}", fixed(ratio)
            else:
                reason = "; ".join(theirs.get("error", [])) or "not measured"
                theirs_s, theirs_mb, ratio_s = reason, "-", "-"
            body.append([count(c["instances"]), f"{c['size']}x{c['size']}", fixed(ours["seconds"], 3),
                         f"{ours['peak_mb']:.0f}", theirs_s, theirs_mb, ratio_s])
        out += ["### Cost of an optimisation step", "", paragraph(GRADIENT_COST), ""]
        out += [table(["instances", "image", "ours s/step", "ours MB", "Mitsuba s/step", "Mitsuba MB",
                       "Mitsuba / ours"], body, "rlrrrrr"), ""]
        if ratios:
            out += [f"Ours is {span(ratios, times)} faster wherever Mitsuba finishes.", ""]
    return out


def _mitsuba_comparison(m: dict, title: str, text: str) -> list[str]:
    """A gradient_mitsuba entry: time and error per sample count, and the equal-error speed-up."""
    out = [f"### {title}", "", paragraph(text.format(size=m["size"], max_depth=m.get("max_depth"))), ""]
    body = [[model, str(r["spp"]), fixed(r["ours_s"], 3), percent(r["ours_error"]),
             fixed(r["mitsuba_s"], 3), percent(r["mitsuba_error"])]
            for model, v in m["models"].items() for r in v["rows"]]
    out += [table(["model", "spp", "ours s", "ours error", "Mitsuba s", "Mitsuba error"], body,
                  "lrrrrr"), ""]
    for model, v in m["models"].items():
        lowest = (min(r["ours_error"] for r in v["rows"]), min(r["mitsuba_error"] for r in v["rows"]))
        speedup = v["speedup_equal_error"]
        line = (f"equal-error speed-up {times(speedup)}" if is_number(speedup)
                else f"no error both reach: lowest {percent(lowest[0])} ours, "
                     f"{percent(lowest[1])} Mitsuba's")
        # Below Mitsuba's lowest error at our fewest samples: compare our cheapest row with
        # Mitsuba's fastest.
        cheapest = min(v["rows"], key=lambda r: r["ours_s"])
        if not is_number(speedup) and cheapest["ours_error"] <= lowest[1]:
            fastest = min(r["mitsuba_s"] for r in v["rows"])
            line += (f"; ours at {cheapest['spp']} spp is already below Mitsuba's lowest error, "
                     f"and Mitsuba's fastest row takes {times(fastest / cheapest['ours_s'])} its time")
        out.append(f"* {model}: {line}")
    return out + [""]


def recovery_section(data: dict) -> list[str]:
    out = []
    bundled = data.get("bundled")
    if bundled:
        out += ["### Transform recovery", "", paragraph(RECOVERY_METHOD)]
        out[-1] += (f" In this run: {bundled['iterations']} iterations at {bundled['spp']} spp, "
                    f"{fixed(bundled['seconds_per_iteration'])} s per iteration.")
        out.append("")
        body = []
        for name in bundled["initial"]:
            a, b = bundled["initial"][name], bundled["final"][name]
            body.append([name, f"{a[0]:.3f} -> {b[0]:.4f}", f"{a[1]:.1f} -> {b[1]:.2f}",
                         f"{a[2]:.3f} -> {b[2]:.3f}", verdict(bundled["met"][name])])
        out += [table(["instance", "translation / size", "rotation (deg)", "scale (largest axis error)",
                       "targets"], body, "lrrrl"), ""]
    shadowed = data.get("shadow")
    if shadowed:
        out += [paragraph(RECOVERY_SHADOW.format(light=", ".join(f"{v:g}" for v in shadowed["light"]))), ""]
        body = []
        for label in [k for k in shadowed if k != "light"]:
            run = shadowed[label]
            for name in run["initial"]:
                b = run["final"][name]
                body.append([label, name, f"{b[0]:.4f}", f"{b[1]:.2f}", f"{b[2]:.3f}",
                             verdict(run["met"][name]), fixed(run["seconds_per_iteration"])])
        out += [table(["gradients", "instance", "translation / size", "rotation (deg)",
                       "scale", "targets", "s / iteration"], body, "llrrrlr"), ""]
    coarse = data.get("coarse")
    if coarse:
        out += [paragraph(RECOVERY_COARSE), ""]
        out += [table(["loss", "before", "after"],
                      [[name, sig(v["initial"]), sig(v["final"])] for name, v in coarse.items()],
                      "lrr"), ""]
    steps = data.get("steps")
    if steps:
        out += [paragraph(RECOVERY_STEPS), ""]
        out += [table(["optimised instances", "optimiser keys", "first step s", "later steps s",
                       "recordings"],
                      [[count(r["optimised"]), str(r["keys"]), fixed(r["first_s"], 1),
                        fixed(r["later_s"], 3), str(r["recordings"])] for r in steps], "rrrrr"), ""]
    many = data.get("many")
    if many:
        seen = (f"; its bounding box {many['object_pixels']:.0f} pixels across in a view (median), "
                f"{many['object_views_cut']} of {many['views'] * many['instances']} object views "
                "cut by a film edge" if "object_pixels" in many else "")
        out += [paragraph(RECOVERY_MANY.format(**many, seen=seen)), ""]
        out += [table(["", "translation / size", "rotation (deg)", "scale"],
                      [["start, largest", *(sig(v) for v in many["start_max"])],
                       ["recovered, median", *(sig(v) for v in many["final_median"])],
                       ["recovered, largest", *(sig(v) for v in many["final_max"])]], "lrrr"), ""]
        plural = {"box": "boxes", "egg": "ellipsoids"}
        kinds = "; ".join(f"{k['met']} of {k['count']} {plural[name]}"
                          for name, k in many.get("kinds", {}).items())
        out += [paragraph(f"Within 1 % of the size, 1 degree and 1 %: {many['met']} of "
                          f"{many['instances']} instances "
                          f"({verdict(many['met'] == many['instances'])}"
                          + (f"; {kinds}" if kinds else "") + "); "
                          f"{fixed(many['seconds_per_iteration'])} s per iteration."), ""]
        if many.get("failed"):
            out += [table(["missed", "translation / size", "rotation (deg)", "scale",
                           "closest axes differ by"],
                          [[f"`{f['id']}`", *(sig(v) for v in f["errors"]),
                            f"{100 * f['axis_gap']:.1f} %"] for f in many["failed"]], "lrrrr"), ""]
    rotation = data.get("rotation")
    if rotation:
        out += [paragraph(RECOVERY_ROTATION.format(iterations=rotation["iterations"],
                                                   spp=rotation["spp"])), ""]
        angles = sorted({r["angle"] for r in rotation["rows"]})
        body = []
        for form, summary in rotation["summary"].items():
            finals = [", ".join(sig(r["error"]) for r in rotation["rows"]
                                if r["form"] == form and r["angle"] == a) for a in angles]
            body.append([form, *finals, f"{summary['solved']} of {summary['runs']}"])
        out += [table(["parameterisation", *(f"start {a:g} deg" for a in angles), "within 1 deg"],
                      body, "l" + "r" * (len(angles) + 1)), ""]
    suite = data.get("suite")
    if suite:
        out += [paragraph(RECOVERY_SUITE.format(
            blur_percent=100 * suite["blur"], blur_fraction_percent=100 * suite["blur_fraction"],
            schedule=_schedule(suite),
            **{k: suite[k] for k in ("problems", "iterations", "spp", "sppc", "target_spp",
                                     "width", "mitsuba_problems")})), ""]
        from benchmarks.recovery_suite import failures, summary, target_lines
        out += ["```", *summary(suite["rows"]), *target_lines(suite["rows"]),
                *failures(suite["rows"]),
                "```", "",
                paragraph(RECOVERY_FAILURES.format(width=suite["width"])), ""]
    return out


RECOVERY_STEPS = (
    "Cost against the number of optimised instances (`python -m benchmarks.recovery --part "
    "steps`): a field of boxes and ellipsoids on a floor, four views at 128x128, `direct` at "
    "2 spp, every object's translation, rotation and scale optimised through the scene file's "
    "two batches (one group key per part, `instancing.traverse`). Seconds per "
    "`OptimisationStep` (update, the four renders with their boundary terms, loss, "
    "`dr.backward`, Adam): the first (tracing and recording; compiling too, unless Dr.Jit's "
    "kernel cache holds the kernels from an earlier run, as it did here) and the median of "
    "later ones (replayed).")
RECOVERY_MANY = (
    "{instances} instances recovered jointly from {views} views (`--part many`): the field "
    "above at {width}x{width}, every view framing the whole field (each object resting 0.02 "
    "above the floor{seen}), every object moved by 5 - 10 % of its size, turned by 5 - 10 degrees and "
    "rescaled by 5 - 10 % per axis; targets rendered at {target_spp} spp; {iterations} "
    "iterations at {spp} spp with {sppp} for the silhouettes and {sppi} for the shadows, the "
    "learning rate decaying to {lr_final_ratio} of its start, the mean of the last "
    "{average_fraction} of the iterates returned.")
def _schedule(run: dict) -> str:
    """A recovery run's Adam schedule in words: the learning rate (constant or decaying)
    and the averaged iterates."""
    rate = (f"a constant learning rate of {run['lr']:g}" if run["lr_final_ratio"] == 1
            else f"a learning rate of {run['lr']:g} decaying to {run['lr_final_ratio']:g} of it")
    return f"{rate}, the mean of the last {run['average_fraction']:g} of the iterates returned"


RECOVERY_ROTATION = (
    "Rotation parameterisations (`--part rotation`): a model without rotational symmetry (a "
    "slab with a post and a fin) seen from two cameras, started 30 to 175 degrees off about "
    "random axes (position and scale right), its rotation recovered through the quaternion "
    "that `instancing.traverse` exposes, through a rotation vector and through the 6D form "
    "(Zhou et al. 2019: two vectors, Gram-Schmidt), each applied on top of the start, with "
    "learning rates of about 0.03 radians per step decaying to 30 % over {iterations} "
    "iterations at {spp} spp. Final angle to the target, degrees:")
RECOVERY_SUITE = (
    "Success rates (`python -m benchmarks.recovery --part suite`, "
    "`benchmarks/recovery_suite.py`): {problems} seeded problems, each one object on a floor "
    "(ellipsoid, elliptic cylinder, box, card, torus mesh in turn) moved by 10 - 20 % of its "
    "size, turned by 12.5 - 25 degrees and rescaled by 10 - 20 % per axis, lit at the first "
    "camera or off the cameras (shadow in view), recovered from 1, 2 and 4 views at "
    "{width}x{width} against targets rendered at {target_spp} spp, {iterations} iterations at "
    "{spp} spp with the interior derivative from {sppc} samples of its own (`recover`'s "
    "default), {schedule} (`recover`'s defaults), coarse to fine (the loss's blur "
    "starts at {blur_percent:g} % of the film width and shrinks to none over the first "
    "{blur_fraction_percent:g} % of the run). Success: within 1 % of the size, "
    "1 degree and 1 % on every scale axis. Mitsuba: the first {mitsuba_problems} problems with "
    "`direct_projective`, the object one plain mesh whose vertices the parameters transform "
    "(`benchmarks/recovery_mitsuba.py`), the same schedule and derivative samples, its own "
    "target images; "
    "\"mitsuba plain\": the same without the blur.")

RECOVERY_FAILURES = (
    "The torus mesh's 24 segments map it onto itself every 15 degrees about its axis, so its "
    "sharp loss ripples with that period; the coarse-to-fine blur smooths the ripple out "
    "(without it, two tori of this suite stopped 10 - 14 degrees off, between turned copies). "
    "A start turned by more than 7.5 degrees about that axis lies nearer a turned copy of "
    "the target than the target itself, and the two give the same images but for the scale's "
    "small anisotropy (a few per cent between the ring's axes): a failure line that puts the "
    "result within a degree of a turned copy is such a problem. A failure of another model "
    "either sits near a symmetry (closest axes a few per cent apart: turning the model about "
    "its axis of near-revolution changes its {width}-pixel images by a fraction of a pixel, "
    "and only the rotation is off) or ran away from its start (every part off). Near a "
    "symmetry the loss is shallow, and anything that shifts its optimum shows: the targets' "
    "noise and the gradient's bias. Problem 40 (an ellipsoid whose closest axes differ by "
    "4.8 %, 2 views, in separate runs): with the derivative from the image's own samples it "
    "ended 2.8 degrees off against 256-spp targets and 2.1 - 2.2 against 4 096-spp ones; "
    "with the derivative from samples of its own (`recover`'s `sppc`), 1.37 and "
    "0.88 - 1.0, all with the learning rate decaying to 30 %; at a constant rate (the iterate "
    "mean then centred on the optimum, not lagging behind a slow drift towards it) 0.04 - "
    "0.18 in separate runs.")


MATERIALS_METHOD = (
    "`benchmarks/materials.py`: a forest of {trees} instances of one tree mesh, every tree "
    "wearing its own `roughplastic` (random colour and roughness, so {materials} materials "
    "with the ground), against the same forest in one shared `roughplastic`; {width}x{height} "
    "at {spp} spp, medians of {repeats} renders per form (ours alternating; Mitsuba's "
    "{mitsuba_repeats}, one form loaded at a time, since Dr.Jit dispatches Mitsuba's BSDF "
    "calls over every BSDF object alive). Mitsuba cannot give instances of one shape group "
    "their own BSDF: its per-instance form is one shape group per material, as `to_mitsuba` "
    "exports it. Target: ours within 1.2x of the shared material's time.")


def materials_section(data: dict) -> list[str]:
    out = ["### Per-instance materials", "",
           paragraph(MATERIALS_METHOD.format(trees=count(data["trees"]),
                                             materials=count(data["materials"]["per-instance"]),
                                             width=data["size"][0], height=data["size"][1],
                                             spp=data["spp"], repeats=data["repeats"],
                                             mitsuba_repeats=data["mitsuba_repeats"])), ""]
    def cell(value: Any, fmt: Callable[[Any], str]) -> str:
        return fmt(value) if is_number(value) else "failed" if value else "-"

    body = []
    failures = set()
    for integrator, row in data["integrators"].items():
        ours, theirs = row["ours"], row["mitsuba"]
        failures |= {v for v in theirs.values() if isinstance(v, str)}
        body.append([f"`{integrator}`", fixed(ours["shared"], 3), fixed(ours["per-instance"], 3),
                     times(ours["ratio"]), verdict(ours["ratio"] <= 1.2),
                     cell(theirs["shared"], lambda v: fixed(v, 3)),
                     cell(theirs["per-instance"], lambda v: fixed(v, 3)), cell(theirs["ratio"], times)])
    out += [table(["integrator", "ours shared s", "ours per-instance s", "ratio", "target",
                   "Mitsuba shared s", "Mitsuba per material s", "ratio"], body, "lrrrlrrr"), ""]
    load, theirs_load = data["load_s"], data["mitsuba_load_s"]
    out += [paragraph(f"Load: ours {fixed(load['per-instance'], 1)} s per-instance "
                      f"({fixed(load['shared'], 2)} s shared), most of it the rough coatings' "
                      f"quadrature, one per material; Mitsuba "
                      f"{cell(theirs_load['per-instance'], lambda v: fixed(v, 1) + ' s')} per material "
                      f"({cell(theirs_load['shared'], lambda v: fixed(v, 2) + ' s')} shared)."), ""]
    for failure in sorted(failures):
        out += [paragraph(f"Mitsuba's form failed in its child process: {failure}"), ""]
    probe = data.get("probe")
    if probe:
        theirs = probe["mitsuba"]
        if "failed" in theirs:
            found = f"Mitsuba's failed: {theirs['failed']}"
        else:
            found = (f"Mitsuba's took {fixed(theirs['direct'], 1)} s (`direct`) and "
                     f"{fixed(theirs['path'], 1)} s (`path`) per render, loading in "
                     f"{fixed(theirs['load_s'], 1)} s with a peak of "
                     f"{fixed(theirs['peak_rss_gb'], 1)} GB of memory")
        out += [paragraph(
            f"Where Mitsuba's per-material form still runs (`--probe`): {count(probe['trees'])} "
            f"trees, each its own material, at {probe['size'][0]}x{probe['size'][1]} and "
            f"{probe['spp']} spp: ours took {fixed(probe['ours']['direct'], 3)} s (`direct`) and "
            f"{fixed(probe['ours']['path'], 3)} s (`path`); {found}."), ""]
    return out


def headline(results: dict, gradients: dict | None, public: Sequence[dict] = ()) -> list[str]:
    """The figures a reader wants first, each from the tables below."""
    lines = []
    intersect = results.get("intersect")
    if intersect:
        spheres = _uniform_rows(intersect["rows"], "sphere")
        if 1000 in spheres:
            s = spheres[1000]
            lines.append(f"1 000 instanced spheres: full hit records at {rate(s['ours'])} Mrays/s, "
                         f"{times(_ratio(s['ours'], s['mi_prelim']))} Embree's preliminary rate and "
                         f"{sig(_ratio(s['ours'], s['mi_full']))}x Mitsuba's full `ray_intersect`.")
        if 100000 in spheres:
            s = spheres[100000]
            lines.append(f"100 000 spheres: {rate(s['ours'])} Mrays/s, "
                         f"{times(_ratio(s['ours'], s['mi_prelim']))} Embree's preliminary rate.")
    render = results.get("render")
    if render:
        sp = [r["speedup_variance_model"] for r in render["rows"] if is_number(r["speedup_variance_model"])]
        first = [r["speedup_equal_error"] for r in render["rows"] if is_number(r["speedup_equal_error"])]
        if sp and first:
            integrators = ", ".join(f"`{i}`" for i in dict.fromkeys(r["integrator"] for r in render["rows"]))
            lines.append(f"Rendering at equal error ({integrators}; {len(sp)} scene/integrator pairs): "
                         f"at least {times(min(sp))} Mitsuba's speed, geometric mean "
                         f"{times(geometric_mean(sp))} (variance model; by the first crossing at least "
                         f"{times(min(first))}, geometric mean {times(geometric_mean(first))}).")
    matches = public_matches(public)
    if matches:
        alike = sum(f["verdict"] == "match" for run in public for f in run["files"])
        measured = "" if alike == len(matches) else f", {len(matches)} with a noise measure"
        lines.append(f"Mitsuba's example scenes ({alike} files that both render alike{measured}): our "
                     f"time at equal error {times(geometric_mean(matches))} Mitsuba's (geometric mean; "
                     f"{span(matches, times)}, ours faster on {sum(m < 1 for m in matches)}).")
    scale = results.get("scale")
    if scale and scale["rows"]:
        largest = scale["rows"][-1]
        held = sum(h["per_instance"] for h in largest["held"])
        lines.append(f"{count(largest['instances'])} instances: load {fixed(largest['load_s'], 1)} s, "
                     f"first image {fixed(largest['render_first_s'])} s, {held:.1f} bytes held per instance.")
    meshes = results.get("loading", {}).get("meshes")
    if meshes:
        largest = meshes[-1]
        lines.append(f"One mesh of {count(largest['triangles'])} triangles (PLY) loads in "
                     f"{fixed(largest['ours'])} s, {times(largest['ours'] / largest['mitsuba'], 1)} "
                     f"Mitsuba's {fixed(largest['mitsuba'])} s.")
    if gradients and gradients.get("cost"):
        ratios = [c["mitsuba"]["seconds"] / c["ours"]["seconds"] for c in gradients["cost"]
                  if is_number(c["mitsuba"].get("seconds"))]
        if ratios:
            lines.append(f"Optimisation steps: {span(ratios, times)} faster than Mitsuba's "
                         f"`direct_projective` where it finishes.")
    return [f"* {line}" for line in lines]


CUDA_METHOD = (
    "The same code with `INSTANCING_BACKEND=cuda` on a GPU lent for one session (CI never has "
    "one), beside Mitsuba's `cuda_ad_rgb` variant, whose queries go through OptiX and the GPU's "
    "ray-tracing cores, in the same run. Intersection: `python -m benchmarks.intersect` (random "
    "rays as above, median of the runs; on CUDA `auto` picks the BVH for every scene). Render: "
    "`python -m benchmarks.render_error` (as above), its equal-error summary rows. Backends: "
    "`python -m benchmarks.backends`, hits and same-seed images on CUDA against records saved on LLVM.")


def cuda_section(data: dict) -> list[str]:
    """The CUDA check: intersection and render beside Mitsuba's OptiX variant, backend agreement."""
    out = ["## CUDA", "", paragraph(CUDA_METHOD), "",
           f"Run of {data['date']} on {data['device']}; {data['software']}; "
           f"{count(data['rays'])} rays, median of {data['repeats']}.", ""]
    body = []
    order = ("sphere", "cube", "rectangle", "disk", "cylinder", "mesh")
    for r in sorted(data["intersect"], key=lambda r: (order.index(r["kind"]), r["instances"])):
        body.append([r["kind"], count(r["instances"]), r["picked"], rate(r["grid"]), rate(r["bvh"]),
                     rate(r["mi_prelim"]), fixed(_ratio(r["bvh"], r["grid"])),
                     fixed(_ratio(r["ours"], r["mi_prelim"]))])
    out.append(table(["kind", "instances", "auto picks", "grid", "BVH", "OptiX prelim", "BVH / grid",
                      "auto / OptiX"], body, "lrlrrrrr"))
    versus_optix = [_ratio(r["ours"], r["mi_prelim"]) for r in data["intersect"]]
    out += ["", paragraph(
        f"Against OptiX's preliminary query we trace at {span(versus_optix, times)} of its rate: on "
        "CUDA, Mitsuba's traversal runs in the ray-tracing cores, ours in Dr.Jit kernels; the "
        "\"mesh traversal as fast as Embree\" target is an LLVM one. " + data["intersect_note"][0].upper()
        + data["intersect_note"][1:] + "."), ""]
    render = data["render"]
    body = [[r["scene"], r["integrator"], f"{r['target_error']:.4f} @ {r['target_spp']} spp",
             fixed(r["ours_time_at_target"], 3), fixed(r["mitsuba_time_at_target"], 3),
             fixed(r["speedup_equal_error"]), r["run"]] for r in render["rows"]]
    out.append(f"Render time against error, {render['width']}x{render['height']}, reference Mitsuba "
               f"at {render['reference_spp']} spp (seconds are launch-bound at this size); run: this "
               f"check, or, for the rows it did not reach, the earlier one ({render['earlier']}):")
    out += ["", table(["scene", "integrator", "target error", "ours s", "Mitsuba s",
                       "speed-up at equal error", "run"], body, "llrrrrl"), ""]
    if render["not_reached"]:
        out += ["Reached by neither check in its device time: " + ", ".join(
            f"`{x}`" for x in render["not_reached"]) + ".", ""]
    body = []
    for b in data["backends"]:
        body.append([b["scene"], percent(b["hit/miss agree %"] / 100), percent(b["instance agree %"] / 100),
                     f"{b['t rel 99.9%']:.2g}", f"{b['normal deg 99.9%']:.2g}"]
                    + [f"{b[f'{i} rel RMSE']:.2g} ({b[f'{i} noise']:.2g})" for i in ("aov", "direct", "path")])
    out.append("Backends, CUDA against LLVM: 200 000 random rays per bundled scene, then 96x72 images "
               "at 16 spp with one seed (in brackets: the image's own noise, between two seeds):")
    out += ["", table(["scene", "hit/miss agree", "instance agree", "t rel 99.9 %", "normal deg 99.9 %",
                       "aov rel RMSE", "direct rel RMSE", "path rel RMSE"], body, "lrrrrrrr"), ""]
    tests = data["tests"]
    out.append(paragraph(
        f"Test suite on CUDA: {tests['passed']} passed, {tests['skipped']} skipped, {tests['failed']} "
        f"failed, {tests['errors']} errors ({tests['note']}). Failures of the machine, not the "
        "backend: " + "; ".join(f"{k}: {v}" for k, v in tests["environment_only"].items()) + ". Failures "
        "of the backend, fixed since: " + "; ".join(f"{k}: {v}" for k, v in tests["fixed"].items())
        + f"; after the fixes, {tests['after_fixes']}."))
    out.append("")
    return out


def machines_section(results: dict, others: Sequence[tuple[str, dict | None]]) -> list[str]:
    """Which machine each table's results come from (:mod:`benchmarks.machine`), as recorded
    in the results files; "not recorded" for results older than the records."""
    rows = [(f"`python -m benchmarks`: {part}", results.get(f"{part}_machine"))
            for part in ("intersect", "render", "scale", "loading") if part in results]
    rows += [(name, data.get("machine")) for name, data in others if data]
    named = [(name, machine_line(m) if m else "not recorded") for name, m in rows]
    return ["Machines (the CUDA table's is named in its section):", "", table(["results", "machine"], named, "ll"), ""]


def build_page(results: dict, gradients: dict | None, recovery: dict | None,
               sources: Sequence[str], materials: dict | None = None,
               cuda: dict | None = None, render_filter: dict | None = None,
               public: Sequence[dict] = (), render_sampler: dict | None = None) -> str:
    """The Markdown page for the given results (deterministic)."""
    out = ["# Performance", "",
           f"<!-- Generated by `{COMMAND}` from {', '.join(sources)}; do not edit by hand. -->", "",
           f"*This page is generated by `{COMMAND}` from {', '.join(f'`{s}`' for s in sources)}. "
           "Edit the script or re-run the benchmarks, not the page.*", ""]
    if results.get("quick"):
        out += ["**These results come from a `--quick` run: a smoke test, not figures to quote.**", ""]
    out += ["In short:", ""] + headline(results, gradients, public) + [""]
    out += ["## How the figures are made", "", paragraph(HOW_MEASURED), ""]
    out += machines_section(results, [("gradients", gradients), ("recovery", recovery),
                                      ("materials", materials)]
                             + [("public scenes: " + ", ".join(p["settings"]["folders"]), p) for p in public])
    if "intersect" in results:
        out += intersect_section(results["intersect"])
    if "render" in results:
        out += render_section(results["render"])
    for variant in (render_filter, render_sampler):
        if variant:
            out += render_variant_section(variant)
    if public:
        out += public_section(public)
    if "scale" in results:
        out += scale_section(results["scale"])
    if "loading" in results:
        out += loading_section(results["loading"])
    if gradients:
        out += gradient_section(gradients)
    if recovery:
        out += recovery_section(recovery)
    if materials:
        out += materials_section(materials)
    if cuda:
        out += cuda_section(cuda)
    out += [FINDINGS, "", TRIED, ""]
    return "\n".join(out)


def _load(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.exists() else None


def _relative(path: Path) -> str:
    try:
        return path.resolve().relative_to(ROOT).as_posix()
    except ValueError:
        return path.as_posix()


def main(argv: Sequence[str] | None = None) -> int:
    """Write (or with ``--check`` compare) the page; return the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--gradients", type=Path, default=GRADIENTS)
    parser.add_argument("--recovery", type=Path, default=RECOVERY)
    parser.add_argument("--materials", type=Path, default=MATERIALS)
    parser.add_argument("--cuda", type=Path, default=CUDA)
    parser.add_argument("--render-filter", type=Path, default=RENDER_FILTER)
    parser.add_argument("--render-sampler", type=Path, default=RENDER_SAMPLER)
    parser.add_argument("--public", type=Path, nargs="*", default=list(PUBLIC))
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--check", action="store_true", help="exit 1 when the page differs from the results")
    args = parser.parse_args(argv)
    results = _load(args.results)
    if results is None:
        print(f"performance_page: {args.results} not found; run `python -m benchmarks` first", file=sys.stderr)
        return 2
    gradients, recovery = _load(args.gradients), _load(args.recovery)
    materials, cuda, render_filter = _load(args.materials), _load(args.cuda), _load(args.render_filter)
    render_sampler = _load(args.render_sampler)
    inputs = ((args.gradients, gradients), (args.recovery, recovery), (args.materials, materials),
              (args.cuda, cuda), (args.render_filter, render_filter), (args.render_sampler, render_sampler))
    public = [(path, _load(path)) for path in args.public]
    sources = ([_relative(args.results)] + [_relative(p) for p, d in inputs if d]
               + [_relative(p) for p, d in public if d])
    page = build_page(results, gradients, recovery, sources, materials, cuda, render_filter,
                      [d for _, d in public if d], render_sampler)
    if args.check:
        current = args.out.read_text() if args.out.exists() else ""
        if current != page:
            print(f"performance_page: {_relative(args.out)} is stale; run `{COMMAND}`", file=sys.stderr)
            return 1
        return 0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(page)
    print(f"wrote {_relative(args.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
