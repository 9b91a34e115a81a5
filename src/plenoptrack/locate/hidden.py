"""Stage 5d of the perspective-shift locator: particles the first search missed, found
again in the residual light field, and the last stage's duplicates.

The located particles' images are divided out of the light field, the residual is
searched as the frame was, and each particle found there must explain the frame's own
pixels beside the located ones (:func:`search_residual`); darkness it cannot take apart
from a located particle widens that particle's uncertainty (its companion,
:func:`_note_companion`). :func:`drop_duplicate_particles` removes weakly seen particles
that are one neighbour's image found again.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass

import numpy as np
import pandas as pd

from .._columns import POS_COLUMNS, SIGMA_COLUMNS
from ._assign import _coincident_pairs, _predict_all
from .frame import (_COMPANION, _FIT_CONTRAST, _FIT_ERROR, _FIT_RADIUS, _HIDDEN,
                     FrameContext, ParticleState, _fit_views, _member_diameter,
                     _usable_views)
from ._nearby import ImageSpans, pairs_within
from ._regions import member_axes, one_elongated_body
from .bodies import parallax_px
from .settings import CheckSettings, PerspectiveLocator
from .split import (_coincides, _coinciding, _explains_more, _never_fitted, _two_images,
                    split_gain_bar)
from .triangulate import TriangulationFlag

__all__ = ["search_residual", "drop_duplicate_particles", "EarlierRounds",
           "STRONG_VIEW_FRACTION", "CHANGED_MARGIN_PX"]

CHANGED_MARGIN_PX = 4.0
"""How close (view pixels, beyond the two images' radii) a turned-down candidate's image
must come to the image of a particle a round changed, in some view, to be fitted again
when found again (:meth:`EarlierRounds.forget_near`): the margin of the frame's other
neighbour tests (rim blur and grow tolerance)."""


@dataclass
class EarlierRounds:
    """The candidates the earlier rounds of a frame's hidden-particle search fitted and
    turned down, and near which nothing has changed since (:func:`search_residual` adds
    them; :meth:`forget_near` drops those near a particle a round changed).

    A candidate found again whose images coincide with one of these (median distance
    over the views at most ``ctx.tolerance_px``) is turned down again without a fit: the
    fit would start from the same place beside the same images.

    Attributes
    ----------
    xyz : (T, 3) float ndarray
        Where the residual's solve placed each, mm.
    radius : (T,) float ndarray
        Their image radii, view pixels.
    residual_data : ndarray or None
        The array the last round's residual light field was written into, which the
        next round's overwrites (:func:`~plenoptrack.locate.residual.divide_out_particles`'s
        ``out``): a new array of the light field's size each round would cost its pages
        mapped anew, about 5 % of a pin image's time on hall2019.
    """

    xyz: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    radius: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    residual_data: np.ndarray | None = None

    def add(self, xyz: np.ndarray, radius: np.ndarray) -> None:
        """Add the candidates at ``xyz`` (k, 3), mm, with image radii ``radius`` (k,)."""
        self.xyz = np.vstack([self.xyz, np.asarray(xyz, dtype=float).reshape(-1, 3)])
        self.radius = np.concatenate([self.radius, np.asarray(radius, dtype=float)])

    def forget_near(self, dlfc, views_uv: np.ndarray, xyz: np.ndarray,
                    radius: np.ndarray) -> None:
        """Drop the candidates whose images come within their radius, the changed
        particle's and :data:`CHANGED_MARGIN_PX` of the image of a changed particle
        (``xyz`` (F, 3), mm, image radii ``radius`` (F,), view pixels) in some view of
        ``views_uv`` (V, 2)."""
        if len(self.xyz) == 0 or len(xyz) == 0:
            return
        mine = _predict_all(dlfc, self.xyz, views_uv)
        spans = ImageSpans(mine)
        near = np.zeros(len(self.xyz), dtype=bool)
        for image, r in zip(_predict_all(dlfc, np.asarray(xyz, dtype=float).reshape(-1, 3),
                                         views_uv), np.asarray(radius, dtype=float)):
            near |= spans.meet(mine, image, self.radius + r + CHANGED_MARGIN_PX)
        self.xyz, self.radius = self.xyz[~near], self.radius[~near]


def search_residual(ctx: FrameContext, state: ParticleState, locator: PerspectiveLocator,
                    calibration, locate_residual, *, elongated: bool = True,
                    earlier: EarlierRounds | None = None
                    ) -> tuple[FrameContext, ParticleState, int]:
    """Search again with the located particles' images divided out.

    The model of every located particle's image (its fitted radius and contrast, or its
    regions' shadow and contrast 0.9; with ``elongated``, an elongated particle's regions'
    ellipse besides, :func:`_elongated_silhouettes`) is divided out of the light field
    (:func:`~plenoptrack.locate.residual.divide_out_particles`, pixels a located image
    blocks set to the background), and the residual is segmented, clustered, solved and
    checked as the frame was (``locate_residual(residual)``: None when it finds nothing,
    else the residual's detections, frame context and checked state). A particle found
    there whose images coincide with a located particle's
    (:func:`~plenoptrack.locate.split._coincides`: what the model did not quite explain
    of that image) is dropped, unless it coincides with one located particle alone and
    ``check.hidden_joint`` is on: that particle's image fit may have grown its disc over
    both images, and the two are fitted together (the located one started from its own
    shadow's radius) and kept under the tests of a split (opaque enough, explaining the
    pixels better than the located particle alone by ``check.split_min_gain`` or the
    split's gain bar, images that move apart by a view pixel across the views and stand
    apart in some view or in space, neither one with another particle's image); the
    located particle then takes the pair's fit. Each other one, best seen first, is
    fitted to the frame's own pixels (:func:`~plenoptrack.locate.refine.fit_images`)
    beside the particles located (and those of this search already kept), and kept when
    its image is opaque (``check.split_min_contrast``), explains the pixels better than
    the model without it by ``check.refine_max_model_error**2`` in mean square (the
    split's test, :func:`~plenoptrack.locate.split.split_merged_particles`), and neither
    lies inside a located particle nor overlaps one with images that keep their offset
    across the views (nothing tells those from one elongated image). Where that one
    particle has no image fit of its own (its position the centroid solution's, which
    merged images can misplace), the candidate's image is fitted again in its place and,
    when it explains the pixels better than that particle's image by the same gain, the
    located particle takes it (:meth:`_ResidualSearch.replaces_unfitted`). The kept ones join
    the frame with their regions, their position, sigma and image from the fit
    (``REFINED``; their size too, in
    :func:`~plenoptrack.locate.perspective.measure_particles`: their regions were cut by
    the images divided out). Nothing is searched when every located particle's last image
    fit explains its pixels to within ``check.refine_max_model_error``, the gain a
    particle found must bring (one whose images merge with a located particle's would
    have spoilt that one's fit), and no more than a few views hold regions no located
    image covers (:func:`_may_hide_particles`). With ``earlier`` (the frame's earlier
    rounds), a candidate found again where nothing has changed since a round turned it
    down is not fitted again (:class:`EarlierRounds`); the candidates this search fits
    and turns down are added to it. Returns the frame context over both sets of
    regions, the joined state and the number of particles added.
    """
    earlier = EarlierRounds() if earlier is None else earlier
    search = _ResidualSearch(ctx, state, locator, elongated, earlier)
    if not search.may_hide_particles():
        return ctx, state, 0
    located = locate_residual(search.residual())
    if located is None:
        return ctx, state, 0
    found, _, state2 = located
    search.take_candidates(found, state2)
    # best seen first: a hidden particle cut into two regions by a located one's image
    # can be found twice, and the second is then held beside the first
    for q in search.best_seen_first(np.flatnonzero(search.new)):
        search.admit(q)
    for q in search.best_seen_first(list(search.shared)):
        search.fit_jointly(q)
    turned_down = np.array(sorted(q for q in search.fitted if not search.new[q]), dtype=np.int64)
    earlier.add(state2.positions[turned_down], search.radius2[turned_down])
    return search.joined(calibration)


class _ResidualSearch:
    """The located particles as the hidden-particle search draws them, the candidates
    found in the residual, and the steps of :func:`search_residual`.

    ``held_*`` are the images every fit is made beside: the live located particles
    (rows ``0..L-1``, ``live_rows`` their state rows) and then each candidate admitted.
    ``earlier`` is what the frame's earlier rounds did (:class:`EarlierRounds`),
    ``fitted`` the candidates this search has fitted.
    """

    def __init__(self, ctx: FrameContext, state: ParticleState, locator: PerspectiveLocator,
                 elongated: bool = True, earlier: EarlierRounds | None = None):
        self.ctx, self.state, self.locator = ctx, state, locator
        self.elongated = elongated
        self.earlier = EarlierRounds() if earlier is None else earlier
        self.fitted = set()
        self.settings = locator.check
        table, n = state.table, state.n_particles
        fit_radius = (table[_FIT_RADIUS].to_numpy(float) if _FIT_RADIUS in table.columns
                      else np.full(n, np.nan))
        self.shadow = 0.5 * _member_diameter(ctx.detections, state.owner, n, shadow=True)
        self.radius = np.where(np.isfinite(fit_radius), fit_radius, self.shadow)
        self.contrast = (np.nan_to_num(table[_FIT_CONTRAST].to_numpy(float), nan=0.9)
                         if _FIT_CONTRAST in table.columns else np.full(n, 0.9))
        self.live = (state.live(locator.solve.min_views)
                     & np.isfinite(self.radius) & (self.radius > 0))
        self.fit_error = (table[_FIT_ERROR].to_numpy(float) if _FIT_ERROR in table.columns
                          else np.full(n, np.nan))
        self.never_fitted = _never_fitted(table["flags"].fillna(0).to_numpy(np.int64),
                                          self.fit_error)
        self.views_uv, self.view_rc = _fit_views(ctx)
        self.pred = _predict_all(ctx.dlfc, np.where(self.live[:, None], state.positions, np.nan),
                                 self.views_uv)

    def may_hide_particles(self) -> bool:
        """Whether the frame is worth a search (:func:`_may_hide_particles`)."""
        return _may_hide_particles(self.ctx, self.state, self.live, self.fit_error, self.pred,
                                   self.radius, self.locator)

    def residual(self):
        """The light field with the live particles' images divided out
        (:func:`~plenoptrack.locate.residual.divide_out_particles`)."""
        from .residual import divide_out_particles

        live = self.live
        pred, radius, contrast = self.pred[live], self.radius[live], self.contrast[live]
        edge = self.ctx.image_edge.widths(self.state.positions[live, 2])
        floor = self.settings.hidden_floor
        if not self.elongated:
            return divide_out_particles(self.ctx.lf, self.view_rc, pred, radius, contrast,
                                        floor=floor, edge=edge)
        # an elongated particle's regions reach beyond its fitted disc: the rest of
        # them is its own image too, not a hidden particle's
        k, centres, shapes = _elongated_silhouettes(self.ctx, self.state.owner,
                                                    np.flatnonzero(live), pred, radius)
        discs = np.c_[radius, radius, np.zeros_like(radius)]
        if self.earlier.residual_data is None:       # the frame's first round
            self.earlier.residual_data = np.empty_like(self.ctx.lf.data)
        return divide_out_particles(self.ctx.lf, self.view_rc,
                                    np.concatenate([pred, centres]),
                                    np.r_[radius, shapes[:, 0]],
                                    np.r_[contrast, contrast[k]], floor=floor,
                                    edge=np.vstack([edge, edge[k]]),
                                    axes=np.vstack([discs, shapes]),
                                    out=self.earlier.residual_data)

    def turned_down_before(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows),) bool: the candidates ``rows`` an earlier round fitted and turned
        down where nothing has changed since (:class:`EarlierRounds`)."""
        rows = np.asarray(rows, dtype=np.int64)
        out = np.zeros(len(rows), dtype=bool)
        if len(self.earlier.xyz) == 0 or len(rows) == 0:
            return out
        before = _predict_all(self.ctx.dlfc, self.earlier.xyz, self.views_uv)
        n = len(before)
        a, b = _coincident_pairs(np.concatenate([before, self.pred2[rows]]),
                                 self.ctx.tolerance_px)
        out[b[(a < n) & (b >= n)] - n] = True
        return out

    def take_candidates(self, found: pd.DataFrame, state2: ParticleState) -> None:
        """The residual's particles seen in enough views (``new``), less those an earlier
        round turned down where nothing has changed (:meth:`turned_down_before`) and those
        whose images coincide with a located particle's; those that coincide with one
        alone are ``shared`` (candidate -> live index) for a joint fit, with
        ``check.hidden_joint``."""
        live = self.live
        self.found, self.state2 = found, state2
        self.new = state2.live(self.locator.solve.min_views)
        self.radius2 = 0.5 * _member_diameter(found, state2.owner, state2.n_particles)
        self.pred2 = _predict_all(self.ctx.dlfc, state2.positions, self.views_uv)
        seen = np.flatnonzero(self.new)
        self.new[seen[self.turned_down_before(seen)]] = False
        live_spans = ImageSpans(self.pred[live])
        self.live_rows = np.flatnonzero(live)
        self.shared = {}
        radius2, pred2 = self.radius2, self.pred2
        for q in np.flatnonzero(self.new):
            if not np.isfinite(radius2[q]) or _coincides(pred2[[q]], radius2[[q]],
                                                         self.pred[live], self.radius[live],
                                                         live_spans):
                self.new[q] = False
                if np.isfinite(radius2[q]) and self.settings.hidden_joint:
                    one = _coinciding(pred2[[q]], radius2[[q]], self.pred[live],
                                      self.radius[live], live_spans)
                    if len(one) == 1:
                        self.shared[q] = int(one[0])
        self.positions2 = state2.positions.copy()
        self.fits = {}                 # the fit that admitted each candidate
        self.companions = {}           # located row -> offset to darkness not taken apart
        self.joint = {}                # located row -> its fit with a candidate it swallowed
        self.held_pos = self.state.positions[live]
        self.held_rc = np.c_[self.radius[live], self.contrast[live]]
        self.held_pred, self.held_spans = self.pred[live], live_spans

    def best_seen_first(self, candidates) -> list:
        """``candidates`` ordered by the number of views they were seen in, most first."""
        n_views = self.state2.table["n_views"].to_numpy(float)
        wanted = set(int(q) for q in candidates)
        return [q for q in np.argsort(-n_views, kind="stable") if q in wanted]

    def rehold(self, jl: int, params: np.ndarray, fitted_pred: np.ndarray) -> None:
        """The held image ``jl`` becomes ``params`` (5,), seen at ``fitted_pred`` (V, 2),
        beside every later fit."""
        self.held_pos[jl], self.held_rc[jl] = params[:3], params[3:]
        self.held_pred[jl] = fitted_pred
        self.held_spans.set_rows([jl], fitted_pred[None])

    def hold(self, params: np.ndarray, fitted_pred: np.ndarray) -> None:
        """Hold the images ``params`` (k, 5), seen at ``fitted_pred`` (k, V, 2), beside
        every later fit."""
        self.held_pos = np.vstack([self.held_pos, params[:, :3]])
        self.held_rc = np.vstack([self.held_rc, params[:, 3:]])
        self.held_pred = np.concatenate([self.held_pred, fitted_pred])
        self.held_spans = self.held_spans.extended(fitted_pred)

    def admit(self, q) -> None:
        """Fit candidate ``q`` to the frame's own pixels beside the images held: it must be
        opaque enough and explain them better than those images alone by the split's gain
        (``check.refine_max_model_error**2`` in mean square), and be neither inside a
        located body nor one with a held image (then its darkness is that particle's
        companion); else it leaves ``new``."""
        ctx, dlfc = self.ctx, self.ctx.dlfc
        held_pos, held_rc, held_pred = self.held_pos, self.held_rc, self.held_pred
        near = self.held_spans.meet(held_pred, self.pred2[q],
                                    held_rc[:, 0] + self.radius2[q] + 4.0)
        start = np.array([[self.radius2[q], 0.9]])
        self.fitted.add(q)
        fit = ctx.fit_images((self.views_uv, self.view_rc), self.positions2[[q]], start,
                             held_pos[near], held_rc[near],
                             max_depth_shift=0.1 * ctx.volume_depth_mm,
                             reference=np.array([[*self.positions2[q], self.radius2[q], 0.0]]))
        if not _one_image_explains(fit, self.settings):
            self.new[q] = False
            return
        # Where the fit took it into a particle already located (their bodies overlap in
        # space), or beside one with images that keep their offset across the views
        # (nothing tells those two from one elongated image), it was that particle's
        # image the model had not quite explained.
        fitted_pred = _predict_all(dlfc, fit.params[:, :3], self.views_uv)
        inside = _inside_bodies(dlfc, fit.params[0, :4], held_pos, held_rc[:, 0])
        # merged images need their centres within the sum of the radii in some view
        close = self.held_spans.near(fitted_pred, fit.params[0, 3] + held_rc[:, 0])
        offset = fitted_pred - held_pred[close]                                # (l, V, 2)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)                   # all-NaN rows
            dist = np.nanmedian(np.hypot(offset[..., 0], offset[..., 1]), axis=1)
        merged = ((dist < fit.params[0, 3] + held_rc[close, 0])
                  & (parallax_px(offset) < 1.0))
        if np.any(inside) or np.any(merged):
            touched = inside.copy()
            touched[np.flatnonzero(close)[merged]] = True
            one = np.flatnonzero(touched)
            others = np.flatnonzero(near)
            if (len(one) == 1
                    and self.replaces_unfitted(fit.params, int(one[0]),
                                               others[others != one[0]])):
                self.new[q] = False
                return
            # beside a particle, not inside its body (that was its own image), and not
            # taken apart from it: darkness its fit may have taken in
            for jl in np.flatnonzero(close)[merged]:
                if jl < len(self.live_rows) and not inside[jl]:
                    _note_companion(self.companions, self.live_rows[jl],
                                    fit.params[0, :3] - held_pos[jl])
            self.new[q] = False
            return
        self.positions2[q] = fit.params[0, :3]
        self.fits[q] = _OneImage(fit, 0)
        self.hold(fit.params, fitted_pred)

    def replaces_unfitted(self, start: np.ndarray, jl: int, others: np.ndarray) -> bool:
        """Whether a candidate's image, started at ``start`` (1, 5: x, y, z mm, radius
        view pixels, contrast), is a better image of the located particle held at ``jl``
        than its own; if so that particle takes it.

        Only a live particle that no image fit has explained or tried qualifies: its
        position is the centroid solution's, which images merged with smaller
        neighbours' can misplace. The candidate is fitted in its place (beside the held
        images ``others``, not beside it), and kept when that one image explains the
        pixels better than the located particle's image by the gain a particle found
        must bring (``check.refine_max_model_error**2`` in mean square) and is opaque
        enough; the located particle then takes it as a joint fit's first image."""
        if jl >= len(self.live_rows):
            return False
        j = int(self.live_rows[jl])
        if j in self.joint or not self.never_fitted[j]:
            return False
        ctx = self.ctx
        again = ctx.fit_images((self.views_uv, self.view_rc), start[:, :3],
                               start[:, 3:], self.held_pos[others], self.held_rc[others],
                               max_depth_shift=0.1 * ctx.volume_depth_mm,
                               reference=np.array([[*self.held_pos[jl], *self.held_rc[jl]]]))
        if not (_one_image_explains(again, self.settings) and np.all(np.isfinite(again.sigma))):
            return False
        fitted_pred = _predict_all(ctx.dlfc, again.params[:, :3], self.views_uv)
        self.joint[j] = again
        self.rehold(jl, again.params[0], fitted_pred[0])
        return True

    def fit_jointly(self, q) -> None:
        """A candidate that coincides with one located particle can be a particle that
        one's image fit swallowed (its disc grown over both images): the two are fitted
        together, the located one started from its own shadow's radius, and the pair is
        kept (the located particle takes the pair's first image, ``q`` joins ``new``)
        when it passes the tests of a split (opaque, explains the pixels better than the
        located particle alone, two images apart by their parallax, neither one with
        another held image); else the candidate is that particle's companion, unless it
        lies inside its body."""
        ctx, dlfc, settings = self.ctx, self.ctx.dlfc, self.settings
        jl = self.shared[q]
        j = int(self.live_rows[jl])
        if j in self.joint:
            return
        held_pos, held_rc, held_pred = self.held_pos, self.held_rc, self.held_pred
        shadow = self.shadow[j]
        own = shadow if np.isfinite(shadow) and shadow < held_rc[jl, 0] else held_rc[jl, 0]
        others = np.flatnonzero(self.held_spans.meet(held_pred, self.pred2[q],
                                                     held_rc[:, 0] + self.radius2[q] + 4.0)
                                | self.held_spans.meet(held_pred, held_pred[jl],
                                                       held_rc[:, 0] + held_rc[jl, 0] + 4.0))
        others = others[others != jl]
        self.fitted.add(q)
        fit = ctx.fit_images((self.views_uv, self.view_rc),
                             np.vstack([held_pos[jl], self.positions2[q]]),
                             np.array([[own, held_rc[jl, 1]], [self.radius2[q], 0.9]]),
                             held_pos[others], held_rc[others],
                             max_depth_shift=ctx.volume_depth_mm,
                             reference=np.array([[*held_pos[jl], *held_rc[jl]]]))
        apart = (fit is not None and np.all(np.isfinite(fit.params))
                 and np.all(np.isfinite(fit.sigma))
                 and fit.params[:, 4].min() >= settings.split_min_contrast
                 and _explains_more(fit, fit.reference_error, settings,
                                    split_gain_bar(self.fit_error, settings)))
        if apart:
            fitted_pred = _predict_all(dlfc, fit.params[:, :3], self.views_uv)
            rest = np.setdiff1d(np.arange(len(held_pos)), [jl])
            apart = (_two_images(dlfc, fit.params, fitted_pred)
                     and not _coincides(fitted_pred, fit.params[:, 3], held_pred[rest],
                                        held_rc[rest, 0], self.held_spans.subset(rest)))
        if not apart:
            if not _inside_bodies(dlfc, np.r_[self.positions2[q], self.radius2[q]],
                                  held_pos[[jl]], held_rc[[jl], 0])[0]:
                _note_companion(self.companions, j, self.positions2[q] - held_pos[jl])
            return
        self.joint[j] = fit
        self.rehold(jl, fit.params[0], fitted_pred[0])
        self.positions2[q] = fit.params[1, :3]
        self.fits[q] = _OneImage(fit, 1)
        self.new[q] = True
        self.hold(fit.params[1:], fitted_pred[1:])

    def joined(self, calibration) -> tuple[FrameContext, ParticleState, int]:
        """The frame context over both sets of regions, the state with the located
        particles' companions and joint fits and the admitted candidates appended (their
        position, sigma and image the fit's, ``REFINED``), and the number added."""
        ctx, new, n = self.ctx, self.new, self.state.n_particles
        state = _with_companions(self.state, self.companions)
        table = state.table
        if not new.any() and not self.joint:
            return ctx, state, 0
        if self.joint:
            # the located particles refitted with a particle they had swallowed
            joint = self.joint
            table = table.copy()
            positions = state.positions.copy()
            rows = np.array(sorted(joint))
            positions[rows] = [joint[j].params[0, :3] for j in rows]
            table.loc[rows, list(POS_COLUMNS)] = positions[rows]
            table.loc[rows, list(SIGMA_COLUMNS)] = np.array([joint[j].sigma[0] for j in rows])
            table.loc[rows, _FIT_ERROR] = [joint[j].model_error for j in rows]
            table.loc[rows, _FIT_RADIUS] = [joint[j].params[0, 3] for j in rows]
            table.loc[rows, _FIT_CONTRAST] = [joint[j].params[0, 4] for j in rows]
            flags = table.loc[rows, "flags"].fillna(0).to_numpy(np.int64)
            table.loc[rows, "flags"] = ((flags & ~int(TriangulationFlag.UNEXPLAINED))
                                        | int(TriangulationFlag.REFINED))
            state = dataclasses.replace(state, positions=positions, table=table)
        if not new.any():
            return ctx, state, 0
        # their position, sigma and image are the fit's (REFINED), as a refined particle's
        fits, positions2 = self.fits, self.positions2
        added = self.state2.table.copy()
        rows = np.flatnonzero(new)
        added.loc[rows, list(POS_COLUMNS)] = positions2[rows]
        added.loc[rows, list(SIGMA_COLUMNS)] = np.array([fits[q].sigma for q in rows])
        added.loc[rows, _FIT_ERROR] = [fits[q].model_error for q in rows]
        added.loc[rows, _FIT_RADIUS] = [fits[q].radius for q in rows]
        added.loc[rows, _FIT_CONTRAST] = [fits[q].contrast for q in rows]
        added.loc[rows, "flags"] = (added.loc[rows, "flags"].fillna(0).to_numpy(np.int64)
                                    | int(TriangulationFlag.REFINED))
        added[_HIDDEN] = True
        state2 = dataclasses.replace(self.state2, positions=positions2, table=added)
        # the new particles and their regions join the frame
        index = np.full(state2.n_particles, -1, dtype=np.int64)
        index[new] = n + np.arange(int(new.sum()))
        # The residual's other regions belong to no one. Not even held as merged images:
        # a located particle's image cut by the model divided out would otherwise count
        # toward its size (_size_members).
        owner2 = np.where(state2.owner >= 0, index[np.maximum(state2.owner, 0)], -1)
        detections = pd.concat([ctx.detections, self.found], ignore_index=True)
        joined = ParticleState(
            owner=np.concatenate([state.owner, owner2]),
            initial=np.vstack([state.initial, state2.initial[new]]),
            positions=np.vstack([state.positions, state2.positions[new]]),
            table=pd.concat([table.assign(**{_HIDDEN: False}), state2.table.loc[new]],
                            ignore_index=True))
        return (FrameContext.build(ctx.lf, calibration, detections, self.locator), joined,
                int(new.sum()))


def _elongated_silhouettes(ctx: FrameContext, owner: np.ndarray, rows: np.ndarray,
                           pred: np.ndarray, radius: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The regions of the elongated particles ``rows`` as ellipses, for the residual.

    A particle whose member regions in the fit views make one elongated body
    (:func:`~plenoptrack.locate._regions.one_elongated_body`: elongated the same way in
    every view, not images merged) reaching beyond its image fit's disc (median long
    semi-axis above ``radius`` (len(rows),) view pixels) is drawn with its regions'
    ellipse besides the disc: the median second-moment axes of its regions, their axial
    mean orientation, centred at its image centre ``pred`` (len(rows), V, 2) in each fit
    view shifted by the median offset of its regions' centroids from it.

    Returns
    -------
    k : (K,) int ndarray
        Index into ``rows`` of each elongated particle.
    centres : (K, V, 2) float ndarray
        Its ellipse's centre ``(s, t)`` in each fit view, view pixels.
    axes : (K, 3) float ndarray
        Semi-major and semi-minor axis (view pixels) and angle (radians, from ``s``
        toward ``t``).
    """
    n_v = pred.shape[1]
    none = (np.zeros(0, dtype=np.int64), np.zeros((0, n_v, 2)), np.zeros((0, 3)))
    usable = _usable_views(ctx)
    fit_view = np.cumsum(usable) - 1                 # ctx.views index -> _fit_views index
    index = np.full(max(owner.max(initial=-1), rows.max(initial=-1)) + 1, -1, dtype=np.int64)
    index[rows] = np.arange(len(rows))
    member = np.flatnonzero(owner >= 0)
    member = member[(index[owner[member]] >= 0) & usable[ctx.view[member]]]
    if len(member) == 0:
        return none
    k_owner = np.full(len(owner), -1, dtype=np.int64)
    k_owner[member] = index[owner[member]]
    axes = member_axes(ctx.detections, k_owner, len(rows))
    elongated = one_elongated_body(axes) & (0.5 * axes[:, 0] > radius)
    if not elongated.any():
        return none
    ks = np.flatnonzero(elongated)
    k = k_owner[member]
    offset = ctx.st[member] - pred[k, fit_view[ctx.view[member]]]
    shift = pd.DataFrame({"k": k, "ds": offset[:, 0], "dt": offset[:, 1]}).groupby("k").median()
    return (ks, pred[ks] + shift.loc[ks, ["ds", "dt"]].to_numpy()[:, None, :],
            np.c_[0.5 * axes[ks, :2], axes[ks, 2]])


def _note_companion(companions: dict, row: int, offset: np.ndarray) -> None:
    """Record in ``companions`` (row -> (3,) offset, mm) darkness at ``offset`` from the
    located particle ``row`` that the hidden-particle search found in the residual and
    could not take apart from it, keeping the farthest (laterally) for each particle."""
    row, offset = int(row), np.asarray(offset, dtype=float)
    if not np.all(np.isfinite(offset)):
        return
    known = companions.get(row)
    if known is None or np.hypot(*offset[:2]) > np.hypot(*known[:2]):
        companions[row] = offset


def _with_companions(state: ParticleState, companions: dict) -> ParticleState:
    """``state`` with each particle's companion offset
    (:data:`~plenoptrack.locate.frame._COMPANION` columns) set to the one ``companions`` holds for
    it where that is farther (laterally) than the one an earlier round of the search recorded."""
    if not companions:
        return state
    table = state.table.copy()
    for column in _COMPANION:
        if column not in table.columns:
            table[column] = np.nan
    rows = sorted(companions)
    kept = dict(companions)
    for row, known in zip(rows, table.loc[rows, list(_COMPANION)].to_numpy(float)):
        _note_companion(kept, row, known)          # the farther of the two stays
    table.loc[rows, list(_COMPANION)] = np.array([kept[r] for r in rows])
    return dataclasses.replace(state, table=table)


def _may_hide_particles(ctx: FrameContext, state: ParticleState, live: np.ndarray,
                        fit_error: np.ndarray, pred: np.ndarray, radius: np.ndarray,
                        locator: PerspectiveLocator) -> bool:
    """Whether the frame can hide a particle the search would find: some ``live``
    particle's last image fit leaves more than ``check.refine_max_model_error``
    unexplained (one whose images merge with a located particle's in most views spoils
    that one's fit), or regions no located image covers (``pred`` (P, V, 2), ``radius``
    (P,)) are seen in at least half as many views as a located particle typically is
    (its median ``n_views``, and at least ``solve.min_views``): regions freed when a
    particle built from merged images was dropped are never clustered again, while
    noise specks, seen in a few noisy views, are not worth a search."""
    if not live.any():
        return False                        # nothing to divide out
    if np.any(live & (fit_error > locator.check.refine_max_model_error)):
        return True
    n_views = state.table["n_views"].to_numpy(float)
    enough = max(locator.solve.min_views, 0.5 * float(np.median(n_views[live])))
    return _n_uncovered_views(ctx, state.owner, pred[live], radius[live]) >= enough


def _n_uncovered_views(ctx: FrameContext, owner: np.ndarray, pred: np.ndarray,
                       radius: np.ndarray) -> int:
    """The number of (fit) views holding a region no particle owns (``owner`` < 0,
    unassigned or held back as merged) whose centroid lies inside none of the images
    ``pred`` (P, V, 2) of radius ``radius`` (P,), view pixels, widened by the grow
    tolerance."""
    usable = _usable_views(ctx)
    fit_view = np.cumsum(usable) - 1                 # ctx.views index -> _fit_views index
    free = np.flatnonzero((owner < 0) & usable[ctx.view])
    if len(free) == 0:
        return 0
    if len(pred) == 0:
        return len(np.unique(ctx.view[free]))
    n_v = pred.shape[1]
    reach = radius + ctx.tolerance_px
    q, d, dist = pairs_within(ctx.st[free], fit_view[ctx.view[free]], float(reach.max()),
                              pred.reshape(-1, 2), np.tile(np.arange(n_v), len(pred)))
    covered = np.zeros(len(free), dtype=bool)
    covered[q[dist <= reach[d // n_v]]] = True
    return len(np.unique(ctx.view[free[~covered]]))


def _drop_unexplained_hidden(ctx: FrameContext, state: ParticleState, first: int, n: int,
                             locator: PerspectiveLocator) -> ParticleState:
    """The particles ``first .. first + n - 1`` (found by
    :func:`~plenoptrack.locate.perspective.find_hidden_particles`) whose refit beside all
    the others leaves their pixels unexplained are tested again as they were admitted,
    and dropped unless they pass: fitted to the pixels beside every other particle where
    it now is, the particle must still be opaque enough (``check.split_min_contrast``)
    and explain the pixels better than the model without it by
    ``check.refine_max_model_error**2`` in mean square. What admitted it was a fit that
    explained the pixels; a neighbour's refit since can take that away (the particle was
    the neighbour's image not quite explained), or leave the place unexplained for all of
    them (three particles whose images merge, where the two fitted as a pair are off):
    only in the second case does the particle still earn its place. A particle kept this
    way stays ``UNEXPLAINED``, its position the fit's that admitted it."""
    flags = state.table["flags"].fillna(0).to_numpy(np.int64)
    rows = np.arange(first, first + n)
    bad = rows[(flags[rows] & int(TriangulationFlag.UNEXPLAINED)) > 0]
    return _dropped(state, bad[~_still_explains_more(ctx, state, bad, locator)])


def _dropped(state: ParticleState, rows: np.ndarray) -> ParticleState:
    """``state`` without the particles ``rows``: no position, no views, their centroids
    owned by none."""
    if len(rows) == 0:
        return state
    table = state.table.copy()
    table.loc[rows, "n_views"] = 0
    positions = state.positions.copy()
    positions[rows] = np.nan
    owner = np.where(np.isin(state.owner, rows), -1, state.owner)
    return dataclasses.replace(state, owner=owner, positions=positions, table=table)


def drop_duplicate_particles(ctx: FrameContext, state: ParticleState,
                             locator: PerspectiveLocator) -> ParticleState:
    """Stage 5e: drop weakly seen particles that are one neighbour's image found again.

    In a few views the segmentation can cut one particle's image in two (a highlight
    dividing its dark core): the particle keeps one piece in each, and the other pieces,
    a little off its image on every side, can cluster into a particle of their own, near
    the same line of sight and a fraction of a millimetre off in depth. Such a particle is
    seen in few views, its centroids scatter, and its image fit leaves the pixels
    unexplained. A particle is tested here when it is seen in fewer than
    :data:`STRONG_VIEW_FRACTION` of the valid views, carries ``UNEXPLAINED``, and its
    images come within 4 view pixels of exactly one other particle's, one seen in at least
    that fraction whose own pixels are explained (no ``UNEXPLAINED``), with the two images
    nearly one (median distance over the views below the larger radius); it is dropped
    unless, fitted to the pixels beside every other particle, it still explains them
    (:func:`_still_explains_more`: the tests a particle found in the residual passes).
    A particle whose images meet several others' is not tested: in a crowd the model
    beside it is less exact, and real particles fail the test there (on the accuracy
    matrix's development seeds at 0.05 particles per microlens, testing every such
    particle with one coinciding neighbour dropped 5 true particles, testing those with
    none 17). Nor is one beside an unexplained neighbour:
    that neighbour's centroids may hold two images merged on nearly one line of sight,
    and the weak particle, seen only in the views where the two stand apart, is one of
    them (two 1 mm spheres 15 mm apart in depth on the development seeds).
    """
    table = state.table
    flags = table["flags"].fillna(0).to_numpy(np.int64)
    live = state.live(locator.solve.min_views)
    strong = table["n_views"].to_numpy(float) >= STRONG_VIEW_FRACTION * ctx.lf.view_mask.sum()
    candidates = np.flatnonzero(live & ~strong
                                & ((flags & int(TriangulationFlag.UNEXPLAINED)) > 0))
    if len(candidates) == 0:
        return state
    radius = _drawn_radius(ctx, state)
    drawn = live & np.isfinite(radius) & (radius > 0)
    explained = (flags & int(TriangulationFlag.UNEXPLAINED)) == 0
    views_uv, _ = _fit_views(ctx)
    pred = _predict_all(ctx.dlfc, np.where(drawn[:, None], state.positions, np.nan), views_uv)
    spans = ImageSpans(pred)
    duplicates = []
    for q in candidates[drawn[candidates]]:
        meet = drawn & spans.meet(pred, pred[q], np.nan_to_num(radius) + radius[q] + 4.0)
        meet[q] = False
        if np.count_nonzero(meet) != 1:
            continue
        p = int(np.flatnonzero(meet)[0])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)            # no common view
            dist = np.nanmedian(np.hypot(*(pred[q] - pred[p]).T))
        if strong[p] and explained[p] and dist < max(radius[q], radius[p]):
            duplicates.append(q)
    duplicates = np.asarray(duplicates, dtype=np.int64)
    return _dropped(state, duplicates[~_still_explains_more(ctx, state, duplicates, locator)])


STRONG_VIEW_FRACTION = 0.25
"""A particle with centroids in at least this fraction of the valid views is seen
strongly: the checks of merged images (``check.max_explained_strong``) and of
duplicates (:func:`drop_duplicate_particles`) treat it as real."""


def _drawn_radius(ctx: FrameContext, state: ParticleState) -> np.ndarray:
    """(P,) image radius (view pixels) each particle is drawn with beside others: its
    last image fit's, else its regions' shadow."""
    radius = state.table[_FIT_RADIUS].to_numpy(float)
    shadow = 0.5 * _member_diameter(ctx.detections, state.owner, state.n_particles,
                                    shadow=True)
    return np.where(np.isfinite(radius), radius, shadow)


def _still_explains_more(ctx: FrameContext, state: ParticleState, rows: np.ndarray,
                         locator: PerspectiveLocator) -> np.ndarray:
    """(len(rows),) bool: particle ``rows[i]``, fitted to the view pixels beside every
    other live particle at its current position and image, is opaque enough, lowers
    the mean-square model error of its pixels by ``check.refine_max_model_error**2``
    against the same model without it and stays out of every other particle's body (the
    admission tests of :func:`~plenoptrack.locate.perspective.find_hidden_particles`)."""
    out = np.zeros(len(rows), dtype=bool)
    if len(rows) == 0:
        return out
    settings = locator.check
    table = state.table
    live = state.live(locator.solve.min_views)
    radius = _drawn_radius(ctx, state)
    contrast = np.nan_to_num(table[_FIT_CONTRAST].to_numpy(float), nan=0.9)
    views_uv, view_rc = _fit_views(ctx)
    drawn = live & np.isfinite(radius) & (radius > 0)
    pred = _predict_all(ctx.dlfc, np.where(drawn[:, None], state.positions, np.nan), views_uv)
    spans = ImageSpans(pred)
    for i, q in enumerate(rows):
        xyz, r = state.positions[q], radius[q]
        if not (np.all(np.isfinite(xyz)) and np.isfinite(r) and r > 0):
            continue
        held = drawn & spans.meet(pred, pred[q], np.nan_to_num(radius) + r + 4.0)
        held[q] = False
        fit = ctx.fit_images((views_uv, view_rc), xyz[None], np.array([[r, contrast[q]]]),
                             state.positions[held], np.c_[radius[held], contrast[held]],
                             max_depth_shift=0.1 * ctx.volume_depth_mm,
                             reference=np.array([[*xyz, r, 0.0]]))
        # a fit that moved into a neighbour's body explains that neighbour's pixels
        out[i] = (_one_image_explains(fit, settings)
                  and not _inside_bodies(ctx.dlfc, fit.params[0, :4], state.positions[held],
                                         radius[held]).any())
    return out


def _one_image_explains(fit, settings: CheckSettings) -> bool:
    """A one-image fit of a particle found in the residual (``fit_images`` with the
    model without it as reference) is usable, opaque enough
    (``check.split_min_contrast``) and explains its pixels better than the model without
    it by ``check.refine_max_model_error**2`` in mean square."""
    return bool(fit is not None and np.all(np.isfinite(fit.params))
                and fit.params[0, 4] >= settings.split_min_contrast
                and (fit.reference_error ** 2 - fit.model_error ** 2
                     >= settings.refine_max_model_error ** 2))


def _inside_bodies(dlfc, xyzr: np.ndarray, held_xyz: np.ndarray,
                   held_radius_px: np.ndarray) -> np.ndarray:
    """(m,) bool: the particle ``xyzr`` (x, y, z mm and image radius, view pixels) and each
    held particle lie closer in space than the sum of their radii (mm, through the local
    magnification)."""
    both = np.vstack([xyzr[None, :4], np.c_[held_xyz, held_radius_px]])
    radius_mm = both[:, 3] / dlfc.local_magnification(*both[:, :3].T)
    return (np.linalg.norm(held_xyz - xyzr[:3], axis=1) < radius_mm[0] + radius_mm[1:])


@dataclass(frozen=True)
class _OneImage:
    """Image ``k`` of an image fit: its sigma (x, y, z), the fit's model error, its
    radius and contrast."""

    fit: object
    k: int

    @property
    def sigma(self) -> np.ndarray:
        s = self.fit.sigma[self.k]
        return np.where(np.isfinite(s), s, np.nan)

    @property
    def model_error(self) -> float:
        return self.fit.model_error

    @property
    def radius(self) -> float:
        return float(self.fit.params[self.k, 3])

    @property
    def contrast(self) -> float:
        return float(self.fit.params[self.k, 4])
