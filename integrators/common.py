"""Shared machinery of the gradient-domain integrators: properties, passes, splatting, features.

Both ``gdpt`` (hybrid shift) and ``gdpt_rr`` (random replay) trace, for every sample, one base
path in pixel ``p`` and four offset paths in the neighbours ``p + (1,0), (0,1), (-1,0), (0,-1)``
(RIGHT, DOWN, LEFT, UP; image y grows downward). A subclass implements :meth:`sample_paths`,
which returns per-sample estimates; this module turns them into per-pixel buffers:

* ``primal``: with the property ``primal`` = ``"base"``, the mean of the base-path estimate;
  with ``"mis"``, the multiple importance sampling combination of every path that lands in the
  pixel (below).
* ``g[k]``: mean of the MIS-weighted half-gradient estimate ``I(p + shift_k) - I(p)`` of the
  base paths of pixel ``p``. The two halves of every pixel pair are summed::

      dx[y, x] = g_RIGHT[y, x] - g_LEFT[y, x + 1]      (x < W - 1, else 0)
      dy[y, x] = g_DOWN[y, x]  - g_UP[y + 1, x]        (y < H - 1, else 0)

Reducing every sample at its own pixel (``dr.block_sum`` over the contiguous samples of a pixel)
and shifting afterwards needs no atomics and is deterministic.

Primal from every path (``primal="mis"``; Kettunen et al. 2015, and the authors' public
implementation, which also adds the offset paths to the pixels they land in): in the pixel pair
``(p, p + shift_k)`` the base path of ``p`` and the offset path of ``p + shift_k`` that lands in
``p`` share the pair's MIS weights, which sum to 1 per path of ``p`` (the weights the gradients
use; a failed shift gives the base weight 1). Each pair is therefore an unbiased estimator of
``I(p)``, and the primal is their mean over the four pairs of ``p``::

    primal[p] = 1/4 sum_k  w_k(x) f(x)/p(x)  +  w_k(y_k) f(y_k) J/p(x_k)     (pair k exists)
                          f(x)/p(x)   (the base-path estimate)                (pair k does not)

A pair exists iff both pixels are on the film and both trace offsets (a gradient mask: both
masked, as for the gradients; a pixel without offsets keeps its base path alone). Per sample
the base pixel gets its own share (the first line's first terms, :func:`pass_sums`) and each
offset its share ``p[k]`` for the pixel it lands in; the per-pixel sums of ``p[k]`` are shifted
to that pixel afterwards like the gradients. ``var_primal`` is the sum of the variances of the
means of the pixel's own shares and of the four neighbours' shares (independent samples), the
half-buffers split all of them by the parity of their sample's index.

``render()`` returns a ``TensorXf`` of shape ``(H, W, C)``; :meth:`GradientIntegratorBase.channels`
names the channel ranges (``primal``, ``dx``, ``dy``, ``albedo``, ``normal``, ``depth``,
``var_primal``, ``var_dx``, ``var_dy``, and the half-buffers ``primal_a``, ``primal_b``,
``albedo_a``, ..., ``dx_a``, ``dx_b``, ``dy_a``, ``dy_b``), computing only the buffers that were
asked for.

Gradient mask: with :attr:`GradientIntegratorBase.gradient_mask` (an ``(H, W)`` bool numpy
array, film pixels, no tiles: per pixel) a pass traces the masked pixels' samples with their
four offsets and the other pixels' samples as plain paths (one base ray, no offsets), each group
launched on its own compacted wavefront (its pixels' samples only) and scattered back into the
per-pixel sums, so the offset work shrinks with the mask. A wavefront's pixel count is rounded up
to a multiple of 1/:data:`WAVEFRONT_BUCKETS` of the film's (the extra lanes repeat a pixel, run
inactive and are never scattered): a frozen pass records once per bucket, so renders whose masks
differ (a pilot's mask per seed) replay each other's recordings. A gradient ``dx[y, x]`` needs both
MIS halves, ``g_RIGHT`` of ``(x, y)`` and ``g_LEFT`` of ``(x + 1, y)``: it is traced iff both
pixels are masked (:func:`traced_gradients`); an untraced one is 0 with infinite ``var_dx`` /
``var_dy`` and in its halves 0, never read as a measurement.

Half-buffers split the samples of a pixel by the parity of their index in the render (even:
``a``, odd: ``b``, whatever the passes):
two independent estimates of the primal, the features and the gradients from the same samples,
at no extra tracing cost (the input of half-buffer error estimates such as NFOR's, Rousselle et
al. 2016).
"""

from __future__ import annotations

import gc
import warnings
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from .channels import CHANNELS, HALVED
from .properties import read_properties

#: Pixel shifts of the four offset paths, in film pixels (x right, y down).
SHIFTS = ((1, 0), (0, 1), (-1, 0), (0, -1))
RIGHT, DOWN, LEFT, UP = range(4)

#: Mixed into a pass's seed for the samplers of the plain paths of a masked render (their samples
#: independent of the masked pixels' samples).
_PLAIN_SEED = 0x27D4EB2F

#: A masked render's wavefronts are padded to a multiple of ``ceil(pixels / WAVEFRONT_BUCKETS)``
#: pixels (at most that many idle lanes each; the frozen pass records once per padded size).
WAVEFRONT_BUCKETS = 16

#: Feature buffers and their channel counts, in output order (the halved buffers but the primal).
_FEATURE_CHANNELS = tuple((name, CHANNELS[name]) for name in HALVED if name != "primal")
#: The per-sample half-gradient sums ``g[k]`` (RIGHT, DOWN, LEFT, UP) behind ``dx``/``dy``.
_GRADIENT_SUMS = ("g0", "g1", "g2", "g3")
#: The per-sample primal shares ``p[k]`` of the offset paths (``primal="mis"``), summed at the
#: base pixel and added to the pixel ``p + shift_k`` they land in.
_OFFSET_SHARES = ("p0", "p1", "p2", "p3")


@dataclass
class PathSamples:
    """Per-sample outputs of :meth:`GradientIntegratorBase.sample_paths` (all length N)."""

    primal: mi.Spectrum
    gradients: list  # four mi.Spectrum half-gradients (RIGHT, DOWN, LEFT, UP), or []
    albedo: mi.Spectrum | None = None
    normal: mi.Vector3f | None = None
    depth: mi.Float | None = None
    #: Per-sample counts (mi.UInt32) of numerical guards that fired inside ``sample_paths``.
    guards: dict = field(default_factory=dict)
    #: ``primal="mis"`` with offsets: per offset k, the base path's contribution weighted by
    #: pixel pair k's MIS weights (a failed shift: weight 1); the offset's own share is
    #: ``gradients[k] + base_shares[k]``. Else [].
    base_shares: list = field(default_factory=list)


@dataclass
class FeatureState:
    """Loop state of the feature buffers (first vertex with a non-delta BSDF)."""

    albedo: mi.Spectrum
    normal: mi.Vector3f
    depth: mi.Float
    open: mi.Bool  # still following a chain of delta vertices

    @staticmethod
    def zeros(n: int) -> FeatureState:
        return FeatureState(
            albedo=dr.zeros(mi.Spectrum, n),
            normal=dr.zeros(mi.Vector3f, n),
            depth=dr.zeros(mi.Float, n),
            open=dr.full(mi.Bool, True, n),
        )


def update_features(
    feat: FeatureState,
    si: mi.SurfaceInteraction3f,
    bsdf: mi.BSDFPtr,
    ray_d: mi.Vector3f,
    to_camera,
    active: mi.Bool,
    near_specular: mi.Bool | None = None,
) -> None:
    """Record albedo, camera-space normal and path length at the first rough vertex.

    Follows the path through near-specular vertices (delta-only BSDFs such as mirrors and glass,
    and where ``near_specular`` is set, e.g. glossy lobes at or below ``gdpt``'s
    ``shift_threshold``), stops at the first other vertex. A path that escapes records albedo 0,
    normal ``-ray.d`` and depth 0. The albedo is Mitsuba's ``eval_diffuse_reflectance`` clamped
    to [0, 1]: for glossy BSDFs it evaluates the lobe for one direction pair and exceeds 1 by
    orders of magnitude on narrow lobes, which no denoiser expects of an albedo. The normal is the
    shading normal flipped to face the arriving ray, in the sensor's camera's view frame: +x
    image right, +y image up, +z towards the viewer (so normals facing the camera have z > 0).
    """
    hit = active & feat.open & si.is_valid()
    miss = active & feat.open & ~si.is_valid()
    rough = hit & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
    if near_specular is not None:
        rough &= ~near_specular
    feat.depth = dr.select(hit, feat.depth + si.t, feat.depth)

    n = si.sh_frame.n
    n = dr.select(dr.dot(n, ray_d) > 0, -n, n)
    albedo = dr.clip(bsdf.eval_diffuse_reflectance(si, rough), 0.0, 1.0)
    feat.albedo = dr.select(rough, albedo, feat.albedo)
    feat.normal = dr.select(rough, _to_view(to_camera, n), feat.normal)

    feat.normal = dr.select(miss, _to_view(to_camera, -ray_d), feat.normal)
    feat.albedo = dr.select(miss, 0.0, feat.albedo)
    feat.depth = dr.select(miss, 0.0, feat.depth)
    feat.open &= ~(rough | miss) & active


def _to_view(to_camera, v: mi.Vector3f) -> mi.Vector3f:
    """World vector -> view frame (Mitsuba's sensor frame is +x left, +y up, +z forward)."""
    c = to_camera @ v
    return mi.Vector3f(-c.x, c.y, -c.z)


def safe_div(a, b):
    """``a / b`` where ``b != 0`` and the quotient is finite, else 0 (float32-safe division)."""
    q = a / dr.select(b != 0, b, 1)
    return dr.select((b != 0) & dr.isfinite(q), q, 0)


#: Plugin classes the shift mappings handle (Mitsuba ``class_name()``), tested in the suite.
#: Nested BSDFs (inside masks, bump and normal maps, blends, two-sided) are checked too.
SUPPORTED_BSDFS = frozenset(
    {
        "SmoothDiffuse",
        "RoughConductor",
        "SmoothConductor",
        "RoughPlastic",
        "SmoothPlastic",
        "SmoothDielectric",
        "RoughDielectric",
        "ThinDielectric",
        "TwoSidedBRDF",
        "Principled",
        "MaskBSDF",
        "BumpMap",
        "NormalMap",
        "BlendBSDF",
    }
)
SUPPORTED_EMITTERS = frozenset(
    {
        "AreaLight",
        "PointLight",
        "SpotLight",
        "DirectionalEmitter",
        "ConstantBackgroundEmitter",
        "EnvironmentMapEmitter",
        "SunskyEmitter",
    }
)


def _bsdf_tree(bsdf: mi.BSDF) -> list[mi.BSDF]:
    """``bsdf`` and every BSDF nested in it (depth first), found through ``traverse()``."""

    class Children(mi.TraversalCallback):
        def __init__(self):
            super().__init__()
            self.found = []

        def put(self, name, value, *flags):
            if isinstance(value, mi.BSDF):
                self.found.append(value)

    children = Children()
    bsdf.traverse(children)
    return [bsdf, *(b for child in children.found for b in _bsdf_tree(child))]


def check_variant(plugin: str) -> None:
    """Refuse a Mitsuba variant the integrators do not render correctly.

    The buffers are three colour channels per pixel (:data:`~.channels.CHANNELS`) computed from
    an RGB ``mi.Spectrum``: spectral variants sample wavelengths the buffers do not carry (an
    ``IndexError`` in Mitsuba 3.9.1), ``mono`` ones hold one channel and polarized ones a
    Mueller matrix. JIT (``llvm_*``/``cuda_*``) variants only: :func:`gdpt.integrators.register`.

    Raises:
        ValueError: naming the active variant and the supported ones.
    """
    if not mi.is_rgb or mi.is_polarized:
        raise ValueError(
            f"{plugin}: the Mitsuba variant '{mi.variant()}' is not supported; the "
            "integrators render RGB buffers: use llvm_ad_rgb or cuda_ad_rgb"
        )


def _medium_name(medium: mi.Medium) -> str:
    return f"'{medium.id()}' ({medium.class_name()})" if medium.id() else medium.class_name()


def check_scene(scene: mi.Scene, plugin: str) -> None:
    """Refuse scenes with plugins the shift mappings do not handle (instead of a wrong image).

    The paths are traced in vacuum (no medium sampling, no transmittance), so a participating
    medium anywhere is refused: on a sensor, on an emitter, or inside or outside a shape.

    Raises:
        ValueError: naming the unsupported BSDF, emitter or participating medium and where it is.
    """
    media = [
        (sensor.get_medium(), f"on sensor '{sensor.id() or sensor.class_name()}'")
        for sensor in scene.sensors()
    ]
    media += [
        (emitter.get_medium(), f"on emitter '{emitter.id() or emitter.class_name()}'")
        for emitter in scene.emitters()
    ]
    for shape in scene.shapes():
        name = shape.id() or shape.class_name()
        media += [
            (shape.interior_medium(), f"inside shape '{name}'"),
            (shape.exterior_medium(), f"outside shape '{name}'"),
        ]
    for medium, where in media:
        if medium is not None:
            raise ValueError(
                f"{plugin}: participating media are not supported: medium "
                f"{_medium_name(medium)} {where}"
            )
    for shape in scene.shapes():
        name = shape.id() or shape.class_name()
        for bsdf in _bsdf_tree(shape.bsdf()):
            kind = bsdf.class_name()
            if kind not in SUPPORTED_BSDFS:
                raise ValueError(
                    f"{plugin}: BSDF '{kind}' on shape '{name}' is not supported; supported: "
                    f"{', '.join(sorted(SUPPORTED_BSDFS))}"
                )
            # A blend picks its component with the sample's random number, so an offset could
            # not follow a delta lobe of the base deterministically (no invertible shift).
            if kind == "BlendBSDF" and mi.has_flag(bsdf.flags(), mi.BSDFFlags.Delta):
                raise ValueError(
                    f"{plugin}: BSDF 'BlendBSDF' on shape '{name}' blends a delta (smooth) "
                    "component, which has no invertible shift; blend rough components only "
                    "(e.g. roughconductor / roughdielectric with a small alpha)"
                )
    for emitter in scene.emitters():
        if emitter.class_name() not in SUPPORTED_EMITTERS:
            raise ValueError(
                f"{plugin}: emitter '{emitter.class_name()}' is not supported; supported: "
                f"{', '.join(sorted(SUPPORTED_EMITTERS))}"
            )


class GradientIntegratorBase(mi.SamplingIntegrator):
    """Common properties and ``render()`` of the gradient-domain integrators.

    Properties: ``max_depth`` (int, 6; -1 = unbounded), ``rr_depth`` (int, 5),
    ``gradients`` (bool, true: trace offset paths; false = plain path tracing with features),
    ``features`` (bool, true), ``variance`` (bool, false),
    ``halves`` (bool, false: also output the primal and features of two independent halves of
    the samples, ``primal_a``/``primal_b``, ..., with ``gradients`` also ``dx_a``/``dx_b``,
    ``dy_a``/``dy_b``; at 1 spp half ``b`` has no sample and is 0),
    ``samples_per_pass`` (int, 2^20: samples traced per kernel launch),
    ``freeze`` (bool, true: replay the recorded kernels of a pass instead of tracing it again),
    ``shift_threshold`` (float, 0.001: microfacet roughness at or below which a glossy vertex
    counts as near-specular; used by ``gdpt``, ignored by ``gdpt_rr``),
    ``primal`` (string, ``"base"``: the base-path estimate; ``"mis"``: every base and offset path
    adds to the pixel it lands in with its pixel pair's MIS weight, see the module docstring;
    without offsets both are the base-path estimate). Their names, types, defaults and valid
    values are one table, :data:`~.properties.PROPERTIES`; the typed values are :attr:`settings`.

    Attribute ``gradient_mask`` (not a property: Mitsuba's properties hold no per-pixel array):
    ``None`` (offsets everywhere) or an ``(H, W)`` bool numpy array of the film's crop, set
    before ``render()``; see the module docstring.
    """

    def __init__(self, props: mi.Properties):
        check_variant(self.plugin_name)
        #: Every property of :data:`~.properties.PROPERTIES`, typed and checked (the one table
        #: of names, types, defaults and valid values).
        self.settings = read_properties(props, self.plugin_name)
        # Removed before the base class sees it: Mitsuba's SamplingIntegrator reads a
        # 'samples_per_pass' of its own and warns that it is deprecated.
        if "samples_per_pass" in props:
            del props["samples_per_pass"]
        super().__init__(props)
        if props.get("hide_emitters", False):
            raise ValueError(f"{self.plugin_name}: 'hide_emitters' is not supported")
        max_depth = self.settings["max_depth"]
        self.max_depth = 0xFFFFFFFF if max_depth == -1 else max_depth
        self.rr_depth = self.settings["rr_depth"]
        self.gradients = self.settings["gradients"]
        self.features = self.settings["features"]
        self.variance = self.settings["variance"]
        self.halves = self.settings["halves"]
        self.samples_per_pass = self.settings["samples_per_pass"]
        self.shift_threshold = self.settings["shift_threshold"]
        self.freeze = self.settings["freeze"]
        self.primal = self.settings["primal"]
        # Replays the kernels of a pass without tracing Python again (dr.freeze): the tracing of
        # the large path loop, its virtual calls over every BSDF and emitter and the kernel
        # hashing cost as much as the kernel itself at 128 px. It records again for new film
        # sizes, spp per pass or settings (the key) and for scenes of another layout. Those
        # recordings are expected (a timing study renders dozens of sample counts per scene),
        # so Dr.Jit's re-tracing warning (after 10 by default, "indicates a problem") is off;
        # tests/gdpt/test_rendering.py checks that a repeated render replays. The 32 most
        # recently used recordings are kept.
        self._frozen_pass = dr.freeze(self._trace_pass, limit=32, warn_after=2**31 - 1)
        # Pass keys whose recording Dr.Jit refused (:meth:`_pass_or_trace`): traced from then on.
        self._unrecordable: set[tuple] = set()
        #: Frozen-pass recordings made by ``render()`` so far, and passes traced because their
        #: recording was refused (a render that adds some traced those passes anew: its time
        #: includes the tracing, and kernel compilation if new).
        self.recordings = 0
        self._traced_unrecordable = 0
        #: Optional ``callable(spp_done, spp_total)`` called after every pass (progress bars).
        self.pass_callback = None
        #: How often each numerical guard fired in the last ``render()``: ``sample_nonfinite``
        #: (per-sample outputs that were not finite and were dropped before accumulation) and
        #: the integrator's own counts (``gdpt``: ``shift_nonfinite``, shifts failed because
        #: their throughput or MIS ratio was not finite; ``term_nonfinite``, gradient terms
        #: dropped). Nonzero counts also raise a ``RuntimeWarning``.
        self.guard_counts: dict[str, int] = {}
        #: Samples per pixel behind the half-buffers ``(a, b)`` of the last ``render()``.
        self.half_spp: tuple[int, int] = (0, 0)
        #: ``None`` or an ``(H, W)`` bool numpy array: the pixels whose samples trace offsets
        #: (needs ``gradients``); read by ``render()``.
        self.gradient_mask: np.ndarray | None = None
        #: The pixel mask the last ``render()`` used: ``None`` when every pixel traced offsets
        #: (no mask, an all-True one, or ``gradients`` off).
        self.rendered_gradient_mask: np.ndarray | None = None

    plugin_name = "gradient integrator"

    # ------------------------------------------------------------------ interface
    def sample_paths(self, scene, sensor, sampler, rays, weights, active) -> PathSamples:
        """Trace the base path (``rays[0]``) and, if enabled, the four offsets (``rays[1:]``)."""
        raise NotImplementedError

    def prepare(self, scene: mi.Scene) -> None:
        """Per-scene set-up before the passes of one ``render()`` call (default: nothing)."""

    def properties(self) -> dict:
        """The plugin's properties as a dict for ``mi.load_dict`` (``type`` included): a twin
        with some settings changed is ``mi.load_dict({**self.properties(), "gradients": False})``.
        """
        return {"type": self.plugin_name, **self.settings}

    def channels(self) -> list[tuple[str, int]]:
        """``(buffer name, channel count)`` in the order ``render()`` stores them."""
        out = [("primal", 3)]
        if self.gradients:
            out += [("dx", 3), ("dy", 3)]
        if self.features:
            out += [("albedo", 3), ("normal", 3), ("depth", 1)]
        if self.variance:
            out += [("var_primal", 1)]
            if self.gradients:
                out += [("var_dx", 1), ("var_dy", 1)]
        if self.halves:
            out += [("primal_a", 3), ("primal_b", 3)]
            if self.features:
                out += [(f"{n}_{h}", c) for n, c in _FEATURE_CHANNELS for h in "ab"]
            if self.gradients:
                out += [(f"{n}_{h}", 3) for n in ("dx", "dy") for h in "ab"]
        return out

    def aov_names(self) -> list[str]:
        suffix = {3: "RGB", 1: "Y"}
        names = []
        for name, c in self.channels():
            letters = "XYZ" if name == "normal" else suffix[c]
            names += [f"{name}.{ch}" for ch in letters]
        return names

    # ------------------------------------------------------------------ rendering
    def render(
        self,
        scene: mi.Scene,
        sensor: int | mi.Sensor = 0,
        seed: int = 0,
        spp: int = 0,
        develop: bool = True,
        evaluate: bool = True,
    ) -> mi.TensorXf:
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        film = sensor.film()
        if not film.rfilter().is_box_filter():
            raise ValueError(
                f"{self.plugin_name}: gradient-domain rendering needs a box pixel filter, the film "
                f"uses '{film.rfilter().class_name()}'; add <rfilter type=\"box\"/> to the film"
            )
        if not develop:
            raise ValueError(f"{self.plugin_name}: develop=False is not supported")
        check_scene(scene, self.plugin_name)
        sampler = sensor.sampler().class_name()
        if (self.variance or self.halves) and sampler != "IndependentSampler":
            # Both are per-pixel statistics of independent samples; a stratified or
            # low-discrepancy sampler correlates the samples of a pixel (and rounds the pass
            # sizes of plan_passes to its own counts).
            raise ValueError(
                f"{self.plugin_name}: the variance and half-buffers need independent samples, "
                f"the sensor's sampler is '{sampler}'; use <sampler type=\"independent\"/>"
            )
        self.prepare(scene)
        spp = int(spp) if spp else int(sensor.sampler().sample_count())
        width, height = (int(v) for v in film.crop_size())
        n_pix = width * height
        passes = plan_passes(n_pix, spp, self.samples_per_pass)
        mask = self._pixel_mask(width, height)
        self.rendered_gradient_mask = mask
        flat = None if mask is None else mask.reshape(-1)

        # primal="mis": which pixel pairs of each traced pixel exist (bit k: pair k)
        mis = self.gradients and self.primal == "mis"
        acc = _Accumulator(n_pix, self.gradients, self.features, self.variance, self.halves, mis)
        self.guard_counts = acc.guard_counts
        key = (*self._pass_key(), width, height, *(int(v) for v in film.crop_offset()))
        pairs = None
        if mis:
            bits = pair_bits(np.ones((height, width), bool) if mask is None else mask)
            pairs = bits.reshape(-1)
        if mask is not None:  # (padded pixel indices, pixels, offsets, seed salt) per wavefront
            quantum = -(-n_pix // WAVEFRONT_BUCKETS)
            groups = [
                (_padded(np.flatnonzero(m), quantum), int(m.sum()), offsets, salt)
                for m, offsets, salt in ((flat, True, 0), (~flat, False, _PLAIN_SEED))
                if m.any()
            ]
            group_pairs = [
                mi.UInt32(pairs[np.asarray(pixels)]) if mis and offsets else None
                for pixels, _, offsets, _ in groups
            ]
        elif mis:
            pairs = mi.UInt32(pairs)
        done = 0
        for index, spp_pass in enumerate(passes):
            pass_seed = (int(seed) * 0x9E3779B1 + index) & 0xFFFFFFFF
            if mask is None:
                sums, counts = self._pass_or_trace(
                    scene, sensor, pass_seed, done, spp_pass, key, None, self.gradients, 0, pairs
                )
            else:
                parts = [
                    (
                        pixels,
                        count,
                        *self._pass_or_trace(
                            scene,
                            sensor,
                            pass_seed ^ salt,
                            done,
                            spp_pass,
                            (*key, offsets, dr.width(pixels)),
                            pixels,
                            offsets,
                            count,
                            group_pairs[g],
                        ),
                    )
                    for g, (pixels, count, offsets, salt) in enumerate(groups)
                ]
                sums, counts = _scatter_parts(parts, n_pix)
            acc.add(sums, counts, spp_pass, done)
            done += spp_pass
            if self.pass_callback is not None:
                self.pass_callback(done, spp)
        self.half_spp = (acc.n_a, acc.n - acc.n_a)
        fired = {k: v for k, v in self.guard_counts.items() if v}
        if fired:
            warnings.warn(
                f"{self.plugin_name}: numerical guards fired ({fired}); the affected samples or "
                "shifts were dropped (see guard_counts)",
                RuntimeWarning,
                stacklevel=2,
            )
        traced = None if mask is None else traced_gradients(mask)
        if self.freeze:
            self.recordings = self._frozen_pass.n_recordings + self._traced_unrecordable
        return acc.finish(width, height, self.channels(), traced)

    def _pixel_mask(self, width: int, height: int) -> np.ndarray | None:
        """A copy of :attr:`gradient_mask` checked against the film; ``None`` for no mask or an
        all-True one (the render without a mask, bit for bit).

        Raises:
            ValueError: a mask with ``gradients`` off, or not a bool ``(height, width)`` array.
        """
        mask = self.gradient_mask
        if mask is None:
            return None
        expected = f"a bool numpy array of shape (H, W) = ({height}, {width})"
        if not self.gradients:
            raise ValueError(f"{self.plugin_name}: gradient_mask ({expected}) needs gradients=true")
        if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_:
            raise ValueError(
                f"{self.plugin_name}: gradient_mask must be {expected}, got "
                f"{type(mask).__name__} of {getattr(mask, 'dtype', None)}"
            )
        if mask.shape != (height, width):
            raise ValueError(
                f"{self.plugin_name}: gradient_mask must be {expected}, got shape {mask.shape}"
            )
        return None if mask.all() else mask.copy()

    def _pass_or_trace(
        self, scene, sensor, seed, done, spp, key, pixels, offsets, count=0, pairs=None
    ):
        """:meth:`_pass`, frozen unless ``freeze`` is off or the pass's recording was refused.

        Dr.Jit refuses to record a pass whose virtual calls reach object instances it cannot
        find in the pass's inputs (``record(): validate(): ... virtual function call``): seen
        when the objects of another scene are alive in the process (a serialized-mesh scene
        loaded beside another, meshes unmerged). Such a pass is traced instead, the same
        kernels and result, with a ``RuntimeWarning`` the first time per settings; it counts in
        :attr:`recordings` (its time includes the tracing).

        Python's cyclic garbage collector is paused during the frozen call: an integrator is
        freed only by it (its frozen pass holds its bound method), and an integrator freed while
        another records a pass aborted the process (``Fatal Python error: Aborted`` with
        ``Garbage-collecting`` on top of a recording: seen when a test file whose integrators
        failed to construct ran before one that records)."""
        args = (scene, sensor, seed, done, spp, key, pixels, offsets, count, pairs)
        if not self.freeze:
            return self._pass(self._trace_pass, *args)
        if key not in self._unrecordable:
            collecting = gc.isenabled()
            gc.disable()  # no garbage collection inside a recording (docstring)
            try:
                return self._pass(self._frozen_pass, *args)
            except RuntimeError as err:
                if not _refused_recording(err):  # e.g. Ctrl-C inside the recording
                    raise
                self._unrecordable.add(key)
                warnings.warn(
                    f"{self.plugin_name}: Dr.Jit could not record a frozen pass ({err}); passes "
                    "of these settings are traced instead (the same result, each traced anew). "
                    "Another scene alive in this process can cause it: free the scenes you are "
                    "done with (gdpt.release_scene)",
                    RuntimeWarning,
                    stacklevel=4,
                )
            finally:
                if collecting:
                    gc.enable()
        self._traced_unrecordable += 1
        return self._pass(self._trace_pass, *args)

    def _pass(
        self,
        trace,
        scene,
        sensor,
        seed: int,
        done: int,
        spp: int,
        key,
        pixels,
        offsets,
        count=0,
        pairs=None,
    ):
        """One pass of ``spp`` samples per pixel of ``pixels`` (``mi.UInt32`` film pixel
        indices; ``None``: every pixel), with the four offset rays if ``offsets``: the per-pixel
        sums and guard counts of :func:`pass_sums`, in the order of ``pixels``; only the first
        ``count`` pixels of ``pixels`` are traced (the rest is padding: inactive, sums 0);
        ``pairs``: ``None`` or the :func:`pair_bits` of those pixels (``primal="mis"``)."""
        n_pix = int(dr.prod(sensor.film().crop_size())) if pixels is None else dr.width(pixels)
        # The primary rays are traced outside the frozen pass (Mitsuba 3.9's thinlens
        # camera does not expose all of its variables to dr.freeze; the rays are cheap),
        # with their own sampler: a sampler passed in would be written back after the
        # loop, which re-runs the loop for the sampler's final state.
        ray_sampler = _pass_sampler(sensor, spp, seed ^ _RAY_SEED, n_pix)
        rays, weights = self._primary_rays(sensor, ray_sampler, spp, pixels, offsets)
        path_seed = dr.opaque(mi.UInt32, seed)
        first = dr.opaque(mi.UInt32, done)  # the pass's first sample index (halves' parity)
        # (an opaque lane count: padded wavefronts of one size share a recording)
        lanes = None if pixels is None else dr.opaque(mi.UInt32, count * spp)
        return trace(scene, sensor, path_seed, first, rays, weights, spp, key, lanes, pairs)

    def _trace_pass(
        self,
        scene,
        sensor,
        seed: mi.UInt32,
        first: mi.UInt32,
        rays,
        weights,
        spp: int,
        key,
        lanes,
        pairs=None,
    ):
        """One pass of ``spp`` samples per pixel from the primary ``rays`` (base and offsets,
        with their ``weights``), the path sampler seeded with ``seed``: per-pixel sums and the
        pass's guard counts (:func:`pass_sums`); ``lanes`` (``mi.UInt32`` or ``None``: all): the
        samples traced, the first ones (the others are padding, inactive); ``pairs``: ``None``
        or the :func:`pair_bits` of the traced pixels (``primal="mis"``).

        ``key`` (settings, film size and offset, see :meth:`_pass_key`) is unused here: as an
        argument of the frozen ``_frozen_pass`` it makes a change of any of them record anew.
        """
        n_pix = dr.width(rays[0].d) // spp
        sampler = _pass_sampler(sensor, spp, seed, n_pix)
        active = mi.Bool(True) if lanes is None else dr.arange(mi.UInt32, n_pix * spp) < lanes
        samples = self.sample_paths(scene, sensor, sampler, rays, weights, active)
        return pass_sums(samples, spp, self.variance, self.halves, first, pairs)

    def _pass_key(self) -> tuple:
        """Everything besides the JIT inputs that shapes the kernels of a pass (Python values:
        the frozen pass records again when one of them changes)."""
        return (
            self.max_depth,
            self.rr_depth,
            self.gradients,
            self.features,
            self.variance,
            self.halves,
            self.shift_threshold,
            self.primal,
            *self.prepared_state(),
        )

    def prepared_state(self) -> tuple:
        """Python-side state :meth:`prepare` derived from the scene (default: none)."""
        return ()

    def _primary_rays(
        self, sensor: mi.Sensor, sampler: mi.Sampler, spp: int, pixels=None, offsets=True
    ):
        """Base ray and, with ``offsets``, the four offset rays (same sub-pixel, aperture and
        time samples) of ``spp`` samples per pixel of ``pixels`` (``None``: every pixel)."""
        film = sensor.film()
        size = film.crop_size()
        if pixels is None:
            idx = dr.arange(mi.UInt32, dr.prod(size) * spp)
            idx //= dr.opaque(mi.UInt32, spp)
        else:
            idx = dr.arange(mi.UInt32, dr.width(pixels) * spp) // dr.opaque(mi.UInt32, spp)
            idx = dr.gather(mi.UInt32, pixels, idx)
        pos = mi.Vector2u(idx % size[0], idx // size[0]) + film.crop_offset()
        pos_f = mi.Vector2f(pos) + sampler.next_2d()
        scale = dr.rcp(mi.ScalarVector2f(size))
        offset = -mi.ScalarVector2f(film.crop_offset()) * scale
        aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
        time = mi.Float(sensor.shutter_open())
        if sensor.shutter_open_time() > 0:
            time += sampler.next_1d() * sensor.shutter_open_time()
        wavelength = sampler.next_1d() if mi.is_spectral else mi.Float(0.5)
        shifts = [(0, 0)] + (list(SHIFTS) if offsets else [])
        rays, weights = [], []
        for sx, sy in shifts:
            p = dr.fma(pos_f + mi.Vector2f(sx, sy), scale, offset)
            ray, weight = sensor.sample_ray(time, wavelength, p, aperture)
            rays.append(ray)
            weights.append(weight)
        return rays, weights


def _refused_recording(err: BaseException) -> bool:
    """Whether ``err`` is Dr.Jit refusing to record a frozen function because its virtual
    calls reach instances outside its inputs (its cause says ``validate()`` and ``virtual
    function call``), and not something else raised while recording (a ``KeyboardInterrupt``
    anywhere in the chain: no)."""
    refused, chain = False, []
    seen: BaseException | None = err
    while seen is not None and all(seen is not e for e in chain):
        if isinstance(seen, KeyboardInterrupt):
            return False
        text = str(seen)
        refused |= "validate()" in text and "virtual function call" in text
        chain.append(seen)
        seen = seen.__cause__ or seen.__context__
    return refused


#: Mixed into a pass's seed for the primary-ray sampler (independent of the path sampler's).
_RAY_SEED = 0x5BD1E995


def _pass_sampler(sensor: mi.Sensor, spp: int, seed, n_pix: int) -> mi.Sampler:
    """A clone of the sensor's sampler for ``n_pix`` pixels x ``spp`` samples, seeded."""
    sampler = sensor.sampler().clone()
    sampler.set_sample_count(spp)
    sampler.set_samples_per_wavefront(spp)
    sampler.seed(seed if isinstance(seed, mi.UInt32) else dr.opaque(mi.UInt32, seed), n_pix * spp)
    return sampler


def pass_sums(
    s: PathSamples, spp: int, variance: bool, halves: bool = False, first=0, pairs=None
) -> tuple[dict, dict]:
    """Per-pixel sums of one pass's samples (``spp`` contiguous samples per pixel).

    Returns ``(sums, counts)``: ``sums`` maps ``primal``, ``g0``..``g3``, ``albedo``, ``normal``,
    ``depth``, with ``variance`` the squared luminances ``sq_primal``, ``sq_g0``.., and with
    ``halves`` ``half_primal``, ``half_albedo``, .., ``half_g0``.. (the sums over the pixel's
    samples whose index in the whole render is even; ``first`` is the index of the pass's first
    sample) to lists of per-pixel ``mi.Float`` channels; ``counts`` maps guard names to one-element
    ``mi.UInt32`` totals (``sample_nonfinite``: samples whose buffer was not finite, which
    contribute 0 to that buffer, plus the integrator's own guards).

    With ``s.base_shares`` (``primal="mis"``; ``pairs``: the :func:`pair_bits` of each pixel,
    ``mi.UInt32``), ``primal`` is the base pixel's own share of the MIS primal and ``p0``..``p3``
    (with ``sq_p0``.., ``half_p0``..) the offsets' shares for the pixels they land in (module
    docstring), 0 where the pair does not exist.
    """
    values = {"primal": s.primal}
    for k, g in enumerate(s.gradients):
        values[f"g{k}"] = g
    if s.base_shares:
        n = dr.width(s.primal)
        bits = dr.gather(mi.UInt32, pairs, dr.arange(mi.UInt32, n) // spp)
        own = dr.zeros(mi.Spectrum, n)
        for k, (g, b) in enumerate(zip(s.gradients, s.base_shares, strict=True)):
            pair = (bits & (1 << k)) != 0
            own += dr.select(pair, b, s.primal)
            values[_OFFSET_SHARES[k]] = dr.select(pair, 0.25 * (g + b), 0)
        values["primal"] = 0.25 * own
    if s.albedo is not None:
        values.update(albedo=s.albedo, normal=s.normal, depth=[s.depth])
    bad = mi.UInt32(0)
    for name, v in values.items():
        comps = v if isinstance(v, list) else [v[i] for i in range(dr.size_v(v))]
        ok = dr.isfinite(sum(comps[1:], comps[0]))
        bad += dr.select(ok, 0, 1)
        values[name] = [dr.select(ok, c, 0) for c in comps]
    if variance:
        for name in ("primal", *_GRADIENT_SUMS, *_OFFSET_SHARES):
            if name in values:
                values[f"sq_{name}"] = [dr.square(sum(values[name]) / 3)]
    if halves:
        index = dr.arange(mi.UInt32, dr.width(values["primal"][0])) % spp + first
        even = index % 2 == 0
        halved = ("primal", *(f for f, _ in _FEATURE_CHANNELS), *_GRADIENT_SUMS, *_OFFSET_SHARES)
        for name in (n for n in halved if n in values):
            values[f"half_{name}"] = [dr.select(even, c, 0) for c in values[name]]
    guards = {"sample_nonfinite": bad, **s.guards}
    # One kernel for all outputs: evaluating them one by one (a reduction evaluates its input)
    # would re-run the path loop for each.
    dr.eval(values, guards)
    counts = {k: dr.sum(c) for k, c in guards.items()}
    sums = {name: [dr.block_sum(c, spp) for c in v] for name, v in values.items()}
    dr.eval(sums, counts)
    return sums, counts


def pair_bits(mask: np.ndarray) -> np.ndarray:
    """Which pixel pairs of a ``primal="mis"`` render exist, per pixel of ``mask`` (``(H, W)``
    bool, the pixels that trace offsets): ``(H, W)`` uint32, bit ``k`` set iff pixel ``p`` and
    its neighbour ``p + SHIFTS[k]`` are both on the film and both in ``mask``."""
    height, width = mask.shape
    padded = np.zeros((height + 2, width + 2), bool)
    padded[1:-1, 1:-1] = mask
    bits = np.zeros(mask.shape, np.uint32)
    for k, (sx, sy) in enumerate(SHIFTS):
        neighbour = padded[1 + sy : 1 + sy + height, 1 + sx : 1 + sx + width]
        bits |= (mask & neighbour).astype(np.uint32) << k
    return bits


def traced_gradients(mask: np.ndarray) -> np.ndarray:
    """Which gradients a render with the pixel mask ``mask`` (``(H, W)`` bool) traces:
    ``(H, W, 2)`` bool, ``[..., 0]`` for ``dx``, ``[..., 1]`` for ``dy``. ``dx[y, x]`` is
    traced iff pixels ``(x, y)`` and ``(x + 1, y)`` are both masked (its two MIS halves start
    there), ``dy[y, x]`` iff ``(x, y)`` and ``(x, y + 1)`` are; the last column's ``dx`` and the
    last row's ``dy`` (no gradient) are False."""
    out = np.zeros((*mask.shape, 2), dtype=bool)
    out[:, :-1, 0] = mask[:, :-1] & mask[:, 1:]
    out[:-1, :, 1] = mask[:-1] & mask[1:]
    return out


def _padded(indices: np.ndarray, quantum: int) -> mi.UInt32:
    """The film pixel indices ``indices`` (non-empty) padded with copies of the last one to a
    multiple of ``quantum`` (a wavefront size shared by masks of similar pixel counts)."""
    width = -(-len(indices) // quantum) * quantum
    out = np.full(width, indices[-1], dtype=np.uint32)
    out[: len(indices)] = indices
    return mi.UInt32(out)


def _scatter_parts(parts: list, n_pix: int) -> tuple[dict, dict]:
    """The per-pixel sums of the wavefronts of a masked pass (``(pixels, count, sums, counts)``,
    ``sums`` from :func:`pass_sums`, ``pixels`` the film pixel of each sum, only the first
    ``count`` traced) as sums over all ``n_pix`` pixels (0 where a wavefront has no such sum,
    e.g. the gradient sums of plain paths), and the guard counts added up."""
    sums: dict = {}
    counts: dict = {}
    for pixels, count, part_sums, part_counts in parts:
        traced = dr.arange(mi.UInt32, dr.width(pixels)) < count
        for name, comps in part_sums.items():
            full = sums.setdefault(name, [dr.zeros(mi.Float, n_pix) for _ in comps])
            for dst, c in zip(full, comps, strict=True):
                dr.scatter(dst, c, pixels, traced)
        for name, c in part_counts.items():
            counts[name] = counts[name] + c if name in counts else c
    dr.eval(sums, counts)
    return sums, counts


def plan_passes(n_pixels: int, spp: int, samples_per_pass: int) -> list[int]:
    """Split ``spp`` into passes of at most ``samples_per_pass`` samples (at least 1 spp each):
    full passes of ``P = samples_per_pass // n_pixels`` spp, the rest in powers of two, largest
    first. A frozen pass records once per pass size, so any ``spp`` on a film replays from at
    most ``log2(P) + 2`` recordings (a remainder of its own would record anew for every new
    ``spp``)."""
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    per_pass = max(1, samples_per_pass // max(n_pixels, 1))
    if n_pixels * per_pass > 2**32:
        raise ValueError(f"image of {n_pixels} pixels is too large for one pass")
    full, rest = divmod(spp, per_pass)
    return [per_pass] * full + [1 << k for k in reversed(range(rest.bit_length())) if rest >> k & 1]


class _Accumulator:
    """Per-pixel sums across passes (float64 so that large spp keep their precision)."""

    def __init__(
        self,
        n_pix: int,
        gradients: bool,
        features: bool,
        variance: bool,
        halves: bool = False,
        mis: bool = False,
    ):
        z = lambda c: [dr.zeros(mi.Float64, n_pix) for _ in range(c)]  # noqa: E731
        self.n = 0
        self.n_a = 0  # samples per pixel in half a (those with an even index in the render)
        self.guard_counts: dict[str, int] = {"sample_nonfinite": 0}
        self.sums = {"primal": z(3)}
        # per sample: the half-gradients and, primal="mis" (``mis``), the offsets' primal shares
        per_offset = (*_GRADIENT_SUMS, *(_OFFSET_SHARES if mis else ())) if gradients else ()
        self.sums.update({name: z(3) for name in per_offset})
        if features:
            self.sums.update(albedo=z(3), normal=z(3), depth=z(1))
        self.variance = variance
        if variance:
            self.sums["sq_primal"] = z(1)
            self.sums.update({f"sq_{name}": z(1) for name in per_offset})
        self.halves = halves
        if halves:
            self.sums["half_primal"] = z(3)
            if features:
                self.sums.update({f"half_{n}": z(c) for n, c in _FEATURE_CHANNELS})
            self.sums.update({f"half_{name}": z(3) for name in per_offset})

    def add(self, sums: dict, counts: dict, spp: int, first: int = 0) -> None:
        """Add one pass's per-pixel sums and guard counts (from :func:`pass_sums`)."""
        for name, acc in self.sums.items():
            for i, c in enumerate(sums.get(name, ())):  # (none: a masked pass traced no offsets)
                acc[i] += mi.Float64(c)
        dr.eval(self.sums)
        for k, c in counts.items():
            self.guard_counts[k] = self.guard_counts.get(k, 0) + int(c[0])
        self.n += spp
        self.n_a += (first + spp + 1) // 2 - (first + 1) // 2  # even indices in the pass

    def finish(self, width: int, height: int, channels, traced=None) -> mi.TensorXf:
        """The ``(height, width, C)`` tensor of ``channels``; ``traced``: ``None`` or the
        :func:`traced_gradients` of a masked render (untraced gradients 0, their variance
        infinite)."""
        n = self.n
        mean = {k: [mi.Float(c / n) for c in v] for k, v in self.sums.items()}
        idx = dr.arange(mi.UInt32, width * height)
        x = idx % width
        y = idx // width
        right_ok = x + 1 < width
        down_ok = y + 1 < height
        # the gradients that exist and were traced (right_ok, down_ok without a mask)
        has_dx, has_dy = right_ok, down_ok
        if traced is not None:
            has_dx = mi.Bool(np.ascontiguousarray(traced[..., 0]).reshape(-1))
            has_dy = mi.Bool(np.ascontiguousarray(traced[..., 1]).reshape(-1))

        def shifted(arr, step, ok):
            return dr.gather(mi.Float, arr, idx + step, ok)

        def var_of_mean(sq_name, lum_mean):
            # Unbiased sample variance of the luminance, divided by n: variance of the mean.
            mean_sq = self.sums[sq_name][0] / n
            var = (mean_sq - mi.Float64(dr.square(lum_mean))) * (n / max(n - 1, 1))
            return mi.Float(dr.maximum(var, 0) / n)

        def differences(g):  # forward differences from the four half-gradient means
            return [
                dr.select(has_dx, g[0][c] - shifted(g[2][c], 1, right_ok), 0) for c in range(3)
            ], [dr.select(has_dy, g[1][c] - shifted(g[3][c], width, down_ok), 0) for c in range(3)]

        # primal="mis": the offset shares p[k] of pixel p land in p + SHIFTS[k]; a pixel gathers
        # them from p - SHIFTS[k] (RIGHT from the left neighbour, ...)
        sources = [
            (idx - 1, x > 0),
            (idx - width, y > 0),
            (idx + 1, right_ok),
            (idx + width, down_ok),
        ]

        def landed(per_offset):  # per_offset[k]: channels of p[k] (or its variance)
            return [
                sum(
                    dr.gather(mi.Float, p[c], source, ok)
                    for p, (source, ok) in zip(per_offset, sources, strict=True)
                )
                for c in range(len(per_offset[0]))
            ]

        mis = "p0" in mean
        out = {"primal": mean["primal"]}
        if mis:
            shares = landed([mean[name] for name in _OFFSET_SHARES])
            out["primal"] = [own + share for own, share in zip(mean["primal"], shares, strict=True)]
        if "g0" in mean:
            out["dx"], out["dy"] = differences([mean[n] for n in _GRADIENT_SUMS])
        for name in ("albedo", "normal", "depth"):
            if name in mean:
                out[name] = mean[name]
        if self.variance:
            lum = lambda k: sum(mean[k]) / 3  # noqa: E731
            out["var_primal"] = [var_of_mean("sq_primal", lum("primal"))]
            if mis:  # own and neighbours' samples are independent: their variances add
                var_shares = landed([[var_of_mean(f"sq_{p}", lum(p))] for p in _OFFSET_SHARES])
                out["var_primal"] = [out["var_primal"][0] + var_shares[0]]
            if "g0" in mean:
                v = [var_of_mean(f"sq_g{k}", lum(f"g{k}")) for k in range(4)]
                # untraced (a masked render): infinite, no information
                missing_x = dr.select(right_ok, dr.inf, 0.0)
                missing_y = dr.select(down_ok, dr.inf, 0.0)
                var_x = v[0] + shifted(v[2], 1, right_ok)
                var_y = v[1] + shifted(v[3], width, down_ok)
                out["var_dx"] = [dr.select(has_dx, var_x, mi.Float(missing_x))]
                out["var_dy"] = [dr.select(has_dy, var_y, mi.Float(missing_y))]

        if self.halves:
            n_a, n_b = self.n_a, n - self.n_a
            for name in ("primal", *(f for f, _ in _FEATURE_CHANNELS)):
                if f"half_{name}" in self.sums:
                    half, total = self.sums[f"half_{name}"], self.sums[name]
                    out[f"{name}_a"] = [mi.Float(h / n_a) for h in half]
                    out[f"{name}_b"] = [  # zeros when half b has no sample (spp 1)
                        mi.Float((t - h) / max(n_b, 1)) for t, h in zip(total, half, strict=True)
                    ]
            if mis:  # each half's offset shares, landed like the primal's
                for which, n_h, part in (
                    ("a", n_a, lambda t, h: h),
                    ("b", max(n_b, 1), lambda t, h: t - h),
                ):
                    shares = landed(
                        [
                            [
                                mi.Float(part(t, h) / n_h)
                                for t, h in zip(self.sums[p], self.sums[f"half_{p}"], strict=True)
                            ]
                            for p in _OFFSET_SHARES
                        ]
                    )
                    out[f"primal_{which}"] = [
                        own + share
                        for own, share in zip(out[f"primal_{which}"], shares, strict=True)
                    ]
            if "half_g0" in self.sums:
                for which, n_h, part in (
                    ("a", n_a, lambda t, h: h),
                    ("b", max(n_b, 1), lambda t, h: t - h),
                ):
                    g = [
                        [
                            mi.Float(part(t, h) / n_h)
                            for t, h in zip(self.sums[k], self.sums[f"half_{k}"], strict=True)
                        ]
                        for k in _GRADIENT_SUMS
                    ]
                    out[f"dx_{which}"], out[f"dy_{which}"] = differences(g)

        comps = [c for name, _ in channels for c in out[name]]
        n_ch = len(comps)
        data = dr.zeros(mi.Float, width * height * n_ch)
        for i, c in enumerate(comps):
            dr.scatter(data, c, idx * n_ch + i)
        return mi.TensorXf(data, shape=(height, width, n_ch))


def camera_transform(sensor: mi.Sensor):
    """World -> sensor-local transform (for camera-space normals)."""
    return sensor.world_transform().inverse()


__all__ = [
    "SHIFTS",
    "GradientIntegratorBase",
    "check_scene",
    "check_variant",
    "PathSamples",
    "FeatureState",
    "update_features",
    "safe_div",
    "plan_passes",
    "pass_sums",
    "traced_gradients",
    "camera_transform",
]
