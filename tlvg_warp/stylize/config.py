"""``StylizeConfig``: every knob of the stylization (SPEC §3), in the config scheme every command shares
(config_io.py): run settings at the top, sections ``loss`` (the terms and their weights), ``geometry``
(advection), ``lr`` (learning rates) and ``density`` (density control). A YAML file states only what it
changes; ``base: other.yaml`` (relative to the file) is loaded first, so an ablation states one thing.
``--set key=value`` takes dotted keys (``loss.w_align=0.1``); the old flat names still load, with a note.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from .. import config_io
from ..config_io import ConfigError, check_run_settings
from ..train.density import DENSITY_RENAMED, DensityConfig
from ..train.optim import LR_RENAMED, LearningRates

PHASES = ("pre", "stylize", "post")


@dataclass
class StyleLoss:
    """The ``loss`` section: the Stylize phase's terms (SPEC §3), weights from the reference code unless marked."""

    style_loss: str = "fast"  # fast (FAST, reference code) | nnfm (ARF) | gram
    luminance_only: bool = True  # style loss on Y = 0.299R+0.587G+0.114B for render and painting (paper §3.3)
    luminance_grad: str = "luma"  # how the luminance-only terms (style on Y, the orientation and stroke terms) push a
    # pixel's colour: luma (Y's own gradient, along (0.299, 0.587, 0.114): a step that raises Y moves Lab a, b about as
    # much as L) | gray (the same Y, its gradient spread evenly over R, G, B: the step runs along the grey axis and
    # leaves the pixel's chroma; ours)
    w_style: float = 2.0  # style loss weight (reference code)
    w_style_color: float = 0.0  # a second style term on RGB features: the painting's colour texture (ours; 0: off)
    w_style_gram: float = 0.0  # a Gram (texture statistics) term on the style term's features: it asks for the
    # painting's strokes over the whole view, where nearest-neighbour matching leaves flat regions smooth (ours; 0: off)
    w_style_coarse: float = 0.0  # a second style term (the same kind, on the same input) one octave coarser: the
    # render and the painting both at half the style term's working size, so VGG's relu3 cells (each sees about 40 of
    # its pixels) span twice as much of the view and the painting; the strokes keep their size relative to the view,
    # while the term sees the painting's larger arrangements of them (swirls, waves) (ours; 0: off; --strength
    # scales it)
    w_style_deep: float = 0.0  # a second style term (the same kind, on the same input) on the conv4 block's features
    # (relu4_1-4_3) instead of the conv3 block's: the painting's statistics at the scale of the Gram distance's deepest
    # layer, which the style term does not see (ours; 0: off; --strength scales it)
    deep_loss: str = "same"  # the deep term: same (the style term's kind) | gram (each conv4 layer's Gram distance)
    # gram: ‖G − G_p‖ / ‖G_p‖ of each layer's Gram matrix against the painting's, averaged over the three layers (the
    # evaluation's Gram distance on them): the layers' texture statistics over the whole view instead of a match per
    # cell (ours)
    strength: float = 1.0  # the style terms' weights times strength cubed (--strength; 1: as set, 0: style terms off)
    # cubed so that the dial's steps look about even over 0-1: multiplied in directly, the painting had taken over by
    # 0.25 on fern (content distance 0.50 / 0.68 / 0.80 / 0.81 at 0 / 0.25 / 1 / 2; docs/study.md)
    w_tone_hold: float = 0.0  # the covered pixels' mean luminance held to the colour target's over the same pixels
    # (the recoloured photo of the view): (Ȳ − Ȳ_target)². The stylize phase lifts a dark object over its target's
    # tone (the biker splats under Monet, a CPU look: 0.526 -> 0.629); with the hold it stays near it (0.53 at 100),
    # the strokes as dark and light around that tone (ours; 0: off)
    tone_margin: float = 0.0  # the tone hold as a hinge: (|Ȳ − Ȳ_target| − margin)² beyond the margin, 0 within it, so
    # the strokes may move the covered tone by up to this much and a scene whose tone holds is not touched (ours)
    tone_cells: int = 0  # the tone hold per cell of a grid this many rows high (square-ish cells), each cell's covered
    # mean against its colour target's, weighted by how much of the cell the scene covers: the view's light and dark
    # masses stay where they were (lego's dark tracks beside its light body) while strokes vary the luminance inside
    # each cell; 0: the whole view's mean alone (ours)
    w_content: float = 0.01  # VGG feature MSE vs the original photo of the view, RGB (reference code)
    content_on: str = "rgb"  # what the content term compares: rgb (the render's and the photo's RGB features) |
    # luminance (their luminance features: with luminance_only the style term's own VGG pass serves it, one image a
    # step instead of two; with an RGB style term the render's luminance joins the batch; ours)
    content_norm: bool = False  # divide the content MSE by the photo features' mean square, per view (ours): the
    # raw MSE scales with how much texture a scene has (relu3 energy of beer's photos is half fern's), so a
    # weight chosen on one scene keeps photo structure unevenly on another; NNFM and FAST are scale-free already
    w_depth: float = 0.01  # MSE of inverse depth vs the un-stylized scene (reference code)
    w_tv: float = 0.02  # total variation of the render, horizontal + vertical (reference code, corrected)
    w_chroma_tv: float = 0.0  # TV of the render's chroma (RGB minus luminance): clean colour patches (ours; 0: off)
    chroma_tv_space: str = "rgb"  # where that chroma is read: rgb (RGB minus luminance) | lab (Lab a*, b* / 200,
    # about the same size on average: a lightness step on a saturated dark colour, which moves a*, b* far more than
    # R - Y, G - Y, B - Y, costs as much as Lab's chroma says; ours)
    w_palette_snap: float = 0.0  # each pixel's chroma pulled to that of the painting colour nearest to it in RGB
    # (k-means of the painting, palette_colours of them): clean colours of the painting's own palette, a stroke's
    # tone choosing which (ours; 0: off; no effect with keep_colors). At 10 and 40 chroma noise rose on every tuning
    # pair measured and beer's floor kept its one tint (docs/study.md), so configs/tlvg.yaml leaves it off
    palette_colours: int = 16  # how many colours the snap term's k-means finds in the painting
    w_style_swd: float = 0.0  # sliced Wasserstein distance between the style term's VGG features of the render and
    # of the painting: the painting's texture as a distribution, every part of it in its own share of the view, where
    # nearest-neighbour matching is content with any close cell (ours; 0: off; --strength scales it)
    w_color_swd: float = 0.0  # sliced Wasserstein distance between the render's RGB colours (where the scene was) and
    # the painting's: its colour distribution (The Starry Night's yellow against its blue), not only its mean and
    # covariance as the palette transfer gives (ours; 0: off; no effect with keep_colors)
    swd_projections: int = 128  # random directions per step of the feature term (768 dimensions)
    color_swd_projections: int = 32  # ... and of the colour term (3 dimensions: 32 cover them; each direction costs
    # a sort of every pixel of the view)
    color_swd_space: str = "rgb"  # what the colour term compares: rgb (colour and brightness) | chroma (RGB minus its
    # luminance Y: the painting's hues in their shares, the scene's tones left to the style and content terms, so a
    # painting's brightest region is not drawn onto an object for its brightness)
    w_coverage: float = 0.0  # hinge on the render's alpha below the un-stylized scene's: no holes open (ours; 0: off)
    w_silhouette: float = 0.0  # hinge on the render's alpha above the un-stylized scene's: splats may not grow into an
    # empty background, where the style terms do not look (ours; 0: off; zero on a capture covered everywhere)
    silhouette_where: str = "all"  # where that hinge counts: all (every pixel whose alpha rises above the un-stylized
    # scene's, inside the object too) | empty (only the pixels the un-stylized scene leaves empty, alpha under 0.5: the
    # outline alone; exactly zero on a capture)
    w_detail: float = 0.0  # hinge (1 - E/E_painting)^2 on the render's luminance detail energy E (what a σ 2 px blur
    # removes, where the scene was) below the painting's at the view's height: nearest-neighbour matching lets a smooth
    # render match the painting's smooth passages, this asks for the painting's level of detail (ours; 0: off)
    w_stroke: float = 0.0  # directional detail hinge: (1 - E_across/T_across)^2 below the painting's luminance contrast
    # across the stroke field, plus (E_along/T_along - 1)^2 above its contrast along it (Scharr gradients weighted by
    # the field's coherence, where the scene was; targets: the painting's own, at the view's height). w_detail asks for
    # contrast in every direction; this asks for stripes that run along the strokes (ours; 0: off)
    stroke_along: str = "ratio"  # the hinge's second half: ratio (E_along/T_along - 1)^2, unbounded, or bounded
    # (1 - T_along/E_along)^2 in [0, 1). A scene with more contrast along the field than the painting (lego's bricks)
    # makes the ratio dominate the loss and smooths its edges (configs/tlvg.yaml uses bounded; docs/study.md); none:
    # the across half alone (an object's studs carry 2-4x the painting's contrast along the field; docs/study.md)
    stroke_where: str = "covered"  # the pixels the stroke hinge weighs: covered (the un-stylized scene's alpha) or
    # interior (that eroded by the gradients' reach: an object's outline against an empty background no longer meets
    # the across half, which then asks the object's own surface for the painting's contrast; ours)
    stroke_contrast: str = "linear"  # the stroke hinge's contrast: on luminance Y (linear) or on log(Y + 0.05) (log)
    # for the render and the painting's target alike: contrast relative to the tone, met in a dark passage by small
    # steps (ours; made against dark objects drifting pale, which it did not prevent: docs/study.md)
    w_orient: float = 0.0  # 1 - the render's own structure-tensor alignment with the stroke field (the flow energy
    # of eq. 1 read off the image instead of the footprints): the texture the style terms paint, not only the splats'
    # axes, follows the painter's directions (ours; 0: off)
    w_opacity_reg: float = 1.0  # ||opacity_logits - value at stylize start||_2 (reference code)
    w_scale_reg: float = 1.0  # ||log_scales - value at stylize start||_2 (reference code)
    w_lab_start: float = 0.2  # Lab chroma statistics weight at the first stylize step (paper, linear schedule)
    w_lab_end: float = 0.05  # ... and at the last stylize step
    lab_sigma: str = "photo"  # the Lab term's target spread of a, b per view: photo (the recolored photo's, the
    # paper) or painting (at least the painting's, channel by channel; ours): a grey photo's recolored targets keep
    # a fraction of the painting's colour contrast, and the term then holds the render to that fraction; keep_colors
    # keeps the photo's
    lab_block: float = 0.0  # the Lab term's statistics on the render and targets averaged over square blocks this
    # fraction of the view's height on a side (ours; 0: per pixel, the paper): a spread of a, b asked of blocks is
    # met by colour patches, while per pixel speckle meets it as well, which chroma TV then fights
    lab_where: str = "all"  # the pixels (blocks) the Lab term reads: all, or covered (those the un-stylized scene
    # covers: an object on an empty background is asked for its own colour statistics, not its background's; ours)
    w_align: float = 2.0  # flow-alignment energy weight (paper eq. 1, ours; configs/tlvg.yaml sets the tuned 8.0)
    w_aniso: float = 0.2  # anisotropy energy weight (across-stroke footprint energy + λmin/λmax, ours)
    field_mapping: str = "matched"  # the flow terms' target: matched (FAST match carries the painting's field) | canvas
    field_canvas: float = 0.0  # with field_mapping matched: the share of the painting's own field, laid over the view
    # as the canvas mapping lays it, in each view's target field (the doubled-angle vectors mixed), so that strokes
    # follow the scene's edges less and the painting's directions more; 0: the matched field alone (the paper), 1:
    # the canvas field (ours)
    field_source: str = "stylize_start"  # what "matched" matches against the painting: the render at the start of
    # stylize (after the pre-process: recoloured, refitted) | unstylized: the un-stylized scene's render, the content
    # the painting is laid over (as `evaluate`'s common field)
    fast_refresh: int = 4  # recompute a view's FAST projection every N of its steps, reusing it between (ours:
    # fern 3000 iterations 7 s faster on the GPU, every metric within its interval, docs/performance.md; 1: every step, as the paper)
    fast_cache: str = "projection"  # what fast_refresh reuses: projection (the top-k cells and the solve) | match (cells only)

    RULES = {"style_loss": ("of", "fast", "nnfm", "gram"), "deep_loss": ("of", "same", "gram"),
             "field_mapping": ("of", "matched", "canvas"),
             "field_source": ("of", "stylize_start", "unstylized"),
             "luminance_grad": ("of", "luma", "gray"), "chroma_tv_space": ("of", "rgb", "lab"),
             "content_on": ("of", "rgb", "luminance"),
             "stroke_along": ("of", "ratio", "bounded", "none"),
             "stroke_contrast": ("of", "linear", "log"), "stroke_where": ("of", "covered", "interior"),
             "lab_sigma": ("of", "photo", "painting"), "lab_block": ("in", 0, 1), "lab_where": ("of", "all", "covered"),
             "silhouette_where": ("of", "all", "empty"),
             "field_canvas": ("in", 0, 1),
             "fast_refresh": (">=", 1), "fast_cache": ("of", "match", "projection"),
             "strength": (">=", 0), "tone_margin": (">=", 0), "tone_cells": (">=", 0), "palette_colours": (">=", 1),
             "swd_projections": (">=", 1),
             "color_swd_projections": (">=", 1), "color_swd_space": ("of", "rgb", "chroma"),
             **{w: (">=", 0) for w in ("w_style", "w_style_coarse", "w_style_deep", "w_style_gram", "w_style_color",
                                       "w_chroma_tv", "w_palette_snap", "w_style_swd", "w_color_swd", "w_tone_hold",
                                       "w_coverage", "w_silhouette", "w_detail", "w_stroke", "w_orient",
                                       "w_content", "w_depth", "w_tv",
                                       "w_opacity_reg", "w_scale_reg",
                                       "w_lab_start", "w_lab_end", "w_align", "w_aniso")}}

    @property
    def style_scale(self) -> float:
        """What ``strength`` multiplies the style terms' weights by."""
        return self.strength ** 3

    def lab_weight(self, k: float, n: int) -> float:
        """Lab chroma weight at stylize step ``k`` (0-based) of ``n``: linear w_lab_start -> w_lab_end."""
        if n <= 1:
            return self.w_lab_start
        t = min(max(k / (n - 1), 0.0), 1.0)
        return self.w_lab_start + (self.w_lab_end - self.w_lab_start) * t


@dataclass
class Geometry:
    """The ``geometry`` section: how positions move during Stylize (the advection branch)."""

    lock_xyz: bool = False  # freeze Gaussian positions during stylize (ABC-GS); False = advection (paper)
    tangential_lambda: float = 1.0  # λ of the tangential update hook (paper eq. 3), in [0, 1]; 0 = off
    max_travel: float = 0.0  # the longest path a splat may take over the stylize phase, in its own footprint widths
    #                          (each step at most max_travel / steps widths); 0 = no limit (paper)

    RULES = {"tangential_lambda": ("in", 0, 1), "max_travel": (">=", 0)}


def _density() -> DensityConfig:
    # in phase steps, every interval, from the first step to the phase's end; no opacity reset. The size rules
    # split, never prune: a fitted scene keeps large splats (background, flat areas; 21% of a small fern fit is
    # over 0.1 x extent); pruning them ("always") opened holes (fern 504x378: 11%), keeping them whole
    # ("after_reset": no holes) left them too coarse to take strokes (fern: flow alignment 0.82 -> 0.53, detail
    # 0.59 -> 0.14). Children keep their parent's mean and covariance (ours: 3DGS splits cracked the demo)
    return DensityConfig(phases=["pre", "stylize"], start=0, until=0, split_mode="moments", size_rules="split",
                         opacity_reset_interval=0, max_gaussians=0, budget_factor=1.2)


def _toggle(phase: str):
    """An old ``density_in_<phase>: bool`` as a change of ``density.phases``."""
    def merge(current: list, on) -> list:
        on = config_io.coerce(f"density_in_{phase}", on, bool)
        return [p for p in PHASES if (p in current and p != phase) or (p == phase and on)]
    return merge


@dataclass
class StylizeConfig:
    iterations: int = 3000  # total optimizer steps, split over the phases in `phases` proportions (paper)
    phases: list[float] = field(default_factory=lambda: [500.0, 2000.0, 500.0])  # relative lengths pre / stylize / post
    seed: int = 0  # seeds the view order, split sampling and torch's RNG
    device: str = "auto"  # cuda, cpu or auto (cuda when available)
    downscale: float = 1.0  # render resolution divisor (dataset images are loaded at 1/downscale)
    palette_init: bool = True  # pre-process starts from the Gaussians recolored by the photos' palette map (ours)
    palette_map: str = "arf"  # how photos and Gaussians take the painting's palette: arf (ARF's mean/covariance
    # transfer) | arf_rank (ours: ARF's map, then luminance moved to the painting's at the same rank, so the clamp to
    # [0,1] does not cut the dark tail ARF maps under 0) | sliced (ours: the photos' colour distribution moved onto
    # the painting's whole distribution, axis by axis over random rotations: a painting's many hues, not their mean) |
    # tone (ours: luminance matched in mean and spread, chroma = the painting's at the same luminance rank; a grey
    # photo is not blown up into pastel tints; losses/palette.py)
    palette_floor: float = 0.0  # arf: a colour variance added to the photos' covariance before whitening (ours; 0 =
    # ARF): a direction the photos barely vary along is stretched by at most sqrt(painting's variance / this)
    palette_where: str = "all"  # arf: the photos' colour statistics over all pixels (ARF) | covered: over the pixels
    # the un-stylized scene covers, weighted by its alpha (ours), so an object on an empty background takes the whole
    # of the painting's palette instead of its dark end (the background claimed the bright end); nearly the same map
    # on a capture (configs/tlvg.yaml sets covered: docs/study.md)
    palette_smooth: float = 0.0  # sliced: its colour displacement averaged over photo colours within this RGB
    # distance (ours; 0 = the map itself), so a grey floor's faint tints move together instead of into far-apart hues;
    # the other maps ignore it (so `--set palette_map=arf` works on a config that sets it)
    palette_focus: float = 0.0  # sliced, smoothed: nearby photo colours sent to the densest place of where the map
    # sent them (mean shift with this RGB width) instead of their mean, so a floor of one colour takes one of the
    # painting's colours, not a grey mix of several (ours; 0 = the mean); ignored without palette_smooth
    post_fresh_adam: bool = False  # the post-process starts Adam's moments for its colours and rotations afresh
    # (ours). With the stylize phase's moments it barely moves toward its targets (the stylized views in the
    # painting's colour statistics: lego x the Rhône's mean luminance 0.300 -> 0.297, afresh 0.206); an option, the
    # Gram distance was worse with it (docs/study.md)
    post_chroma_blur: float = 0.0  # the post-process's targets with their chroma blurred by this fraction of the view's
    # height, luminance kept (ours; 0: off, at most 0.1 so the blur's reflected border fits in a portrait view): ARF's
    # map of each stylized view carries its colour noise, which a post-process that reaches its targets
    # (post_fresh_adam) would paint back
    fit_iterations: int = 7000  # reconstruction steps when only --data is given (the scene is fitted first)
    style: str | None = None  # the painting's path (None: the built-in Starry Night); --style sets it
    style_height: int = 256  # the painting is resized to this height before VGG (SPEC §3); 0: to the height at
    # which VGG sees a view (view height x vgg_scale), i.e. the painting spans the view and its strokes keep their
    # size relative to the picture
    stroke_scale: float = 1.0  # the painting's working size x this: 2 = strokes twice as large in the views
    style_max_cells: int = 0  # > 0: the style terms match each view cell against at most this many of the painting's
    # feature cells (ours), every s-th row and column of its relu3 cells, s the smallest stride that fits; 0: every
    # cell. The match's cost grows with the product of the view's cells and the painting's, and with style_height 0
    # both grow with the view: at 65536 a stylize step at 4 MP took 56.1 ms instead of 201.9 (2 MP: 31.6 instead of
    # 46.1; both before the match's product was aligned), while at fern's 1008x756 a quarter of the cells moved NNFM
    # 0.0006 and the stroke measure 0.002 past three seeds' range, so it is an option (docs/performance.md)
    refine_radius: float = 0.0  # before the pre-process, split splats wider on screen than this x stroke_scale
    # pixels (their mean 3-sigma radius over the views) into stroke-sized children, within the Gaussian budget;
    # 0: off. A flat region held by a few huge splats cannot take a brushstroke (train/refine.py)
    stroke_jitter: float = 0.0  # at the start of stylize, every Gaussian's luminance moves by a random amount of this x
    # the painting's stroke contrast (its luminance high-pass std), chroma unchanged: each splat (already shaped along
    # the field) reads as a stroke of its own tone, as a painter varies the paint per stroke; 0: off
    stroke_jitter_mode: str = "luminance"  # luminance (above) | palette: the offset is this x (a random pixel of the
    # painting minus its mean colour), so strokes take the painting's colours, as its dabs of yellow in the blue |
    # palette_tone: the pixel is drawn from the painting's pixels of the splat's own luminance (16 bands of equal
    # count) and the offset is taken from their mean, so a splat keeps its tone (keep_colors sets luminance)
    keep_colors: bool = False  # keep the scene's own colours: no palette transfer, style on luminance only
    colour_floor: bool = False  # after every step, SH-0 colour channels below 0 are lifted to 0 (ours). The renderer
    # clamps a channel there and passes it no gradient, so a channel pushed under 0 stays dead for the rest of the run
    # (57% of lego x Starry Night's stylized splats had one); no effect with keep_sh. Off here (the paper's method),
    # on in configs/tlvg.yaml (chroma noise down on all five tuning pairs: docs/study.md)
    palette_detail: bool = False  # after the palette transfer, raise the recolored photos' luminance detail toward the
    # painting's (losses.match_detail). Off: on the study it raised detail but lowered flow alignment on one tuning pair
    vgg_weights: str | None = None  # torchvision vgg16 state dict path, "random", or None (env / torch hub cache)
    vgg_scale: float = 0.5  # the render is resized by this before VGG (SPEC §3: x0.5)
    vgg_channels_last: bool = True  # on CUDA: VGG in NHWC (cuDNN's layout; float32 arithmetic, gradients within 3e-4)
    vgg_cuda_graphs: bool = True  # on CUDA: the loss's VGG pass (forward and backward) replays a captured CUDA graph
    terms_cuda_graphs: bool = True  # on CUDA: every term read off the render alone (VGG, content, depth, chroma TV,
    # orientation, stroke, coverage, silhouette, Lab) replays as one captured CUDA graph each way; vgg_cuda_graphs
    # and orient_cuda_graphs apply where it does not (a term it lacks is on: loss.w_style_gram, w_style_swd,
    # w_style_color, w_color_swd, w_palette_snap, w_detail, w_tone_hold; or loss.lab_where covered)
    orient_cuda_graphs: bool = True  # on CUDA: the orientation and stroke terms (loss.w_orient, w_stroke) replay one
    # captured CUDA graph
    keep_sh: bool = False  # keep view-dependent SH bands in stylized.ply (default: degree 0, ~3.6x smaller)
    background: list[float] | None = None  # render background RGB; None: the dataset's (white for the demo)
    views_per_step: int = 1  # training views per step (per rank under torchrun); the loss is their mean
    render_headroom: float = 0.0  # > 1 on a GPU: key buffers sized from a view's last count x this (0: exact counts)
    # A training render then never waits for its intersection count; no faster over a whole run as measured
    # (docs/performance.md)
    log_every: int = 50  # host reads (log flush, progress bar, NaN check, last-good snapshot) every N iterations
    checkpoint_every: int = 0  # also write checkpoint.pt every N iterations (0: by time only, below)
    checkpoint_seconds: float = 60.0  # ... and at the first log point this long after the last one (0: off); a killed run loses about this much; log.jsonl is written at the same point
    web_formats: bool = True  # also write stylized.compressed.ply (SuperSplat/PlayCanvas) and stylized.spz (Niantic)
    orbit_frames: int = 96  # frames of orbit.mp4 (interpolated between the dataset cameras)
    orbit_fps: int = 24  # frame rate of orbit.mp4
    comparison_views: int = 4  # rows of comparison.png
    loss: StyleLoss = field(default_factory=StyleLoss)  # the stylize phase's loss terms and weights
    geometry: Geometry = field(default_factory=Geometry)  # advection during stylize
    lr: LearningRates = field(default_factory=LearningRates)  # learning rates, one Adam across the phases (3DGS)
    density: DensityConfig = field(default_factory=_density)  # adaptive density control, per phase step

    RULES = {"iterations": (">=", 1), "fit_iterations": (">=", 0), "style_height": (">=", 0),
             "stroke_scale": (">", 0), "style_max_cells": (">=", 0), "refine_radius": (">=", 0),
             "stroke_jitter": (">=", 0),
             "stroke_jitter_mode": ("of", "luminance", "palette", "palette_tone"),
             "palette_map": ("of", "arf", "arf_rank", "sliced", "tone"),
             "palette_floor": (">=", 0), "palette_where": ("of", "all", "covered"),
             "palette_smooth": ("in", 0, 1), "palette_focus": ("in", 0, 1), "post_chroma_blur": ("in", 0, 0.1),
             "downscale": (">", 0), "views_per_step": (">=", 1),
             "log_every": (">=", 1), "checkpoint_every": (">=", 0), "checkpoint_seconds": (">=", 0),
             "orbit_frames": (">=", 0), "orbit_fps": (">=", 1), "comparison_views": (">=", 0)}
    RENAMED = {**LR_RENAMED, **DENSITY_RENAMED,
               **{k: f"loss.{k}" for k in ("style_loss", "luminance_only", "w_style", "w_content", "w_depth", "w_tv",
                                           "w_opacity_reg", "w_scale_reg", "w_lab_start", "w_lab_end", "w_align",
                                           "w_aniso", "field_mapping")},
               "lock_xyz": "geometry.lock_xyz", "tangential_lambda": "geometry.tangential_lambda",
               "density_in_pre": ("density.phases", _toggle("pre")),
               "density_in_stylize": ("density.phases", _toggle("stylize")),
               "gaussian_budget": "density.max_gaussians", "budget_factor": "density.budget_factor",
               "use_budget": "density.use_budget"}

    # ------------------------------------------------------------------------------------------------------
    def phase_steps(self) -> tuple[int, int, int]:
        """(pre, stylize, post) step counts summing to ``iterations`` (stylize gets the rounding rest)."""
        p = [max(0.0, float(x)) for x in self.phases]
        tot = sum(p)
        pre = int(round(self.iterations * p[0] / tot))
        post = int(round(self.iterations * p[2] / tot))
        return pre, self.iterations - pre - post, post

    def style_work_height(self, view_height: int) -> int:
        """The painting's working height for views ``view_height`` pixels high (style_height, stroke_scale)."""
        base = self.style_height or view_height * self.vgg_scale
        return max(16, int(round(base * self.stroke_scale)))

    def check(self, prefix: str = "") -> None:
        if len(self.phases) != 3 or any(not (x >= 0 and math.isfinite(x)) for x in self.phases) or sum(self.phases) <= 0:
            raise ConfigError(prefix + "phases", f"must be 3 non-negative numbers (pre, stylize, post), got {self.phases}")
        check_run_settings(self, prefix)
        if self.loss.w_style_coarse > 0 and self.loss.w_style_deep > 0:
            raise ConfigError(prefix + "loss.w_style_deep", "is a second style term like loss.w_style_coarse: set one "
                                                             "of the two")
        if not (isinstance(self.vgg_scale, (int, float)) and 0 < self.vgg_scale <= 4):
            raise ConfigError(prefix + "vgg_scale", f"must be in (0, 4], got {self.vgg_scale}")
        unknown = set(self.density.phases) - set(PHASES)
        if unknown:
            raise ConfigError(prefix + "density.phases", f"must name phases among {', '.join(PHASES)}, got "
                                                         f"{sorted(unknown)}")

    def validate(self) -> "StylizeConfig":
        cfg = config_io.validate(self)
        if cfg.keep_colors:  # the scene's colours: the style may only shape luminance (and the jitter only tone)
            cfg = dataclasses.replace(cfg, loss=dataclasses.replace(cfg.loss, luminance_only=True, w_style_color=0.0,
                                                                               w_color_swd=0.0),
                                      stroke_jitter_mode="luminance")
        return cfg


# --- loading -------------------------------------------------------------------------------------------------
def config_from_dict(d: dict, base: StylizeConfig | None = None) -> StylizeConfig:
    """``base`` (default: the built-in defaults) with the nested or dotted mapping ``d`` (not validated)."""
    return config_io.from_dict(StylizeConfig, d, base)


def load_config(path=None, overrides=(), base: StylizeConfig | None = None) -> StylizeConfig:
    """Defaults (or ``base``), then the YAML file with its ``base:`` chain, then ``key=value`` overrides."""
    return config_io.load(StylizeConfig, path, overrides, base)


def config_yaml(cfg: StylizeConfig, header: str = "tlvg_warp stylize: resolved configuration") -> str:
    return config_io.config_yaml(cfg, header)


__all__ = ["StylizeConfig", "StyleLoss", "Geometry", "PHASES", "load_config", "config_from_dict", "config_yaml"]
