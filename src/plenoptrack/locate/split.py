"""Stage 5c of the perspective-shift locator: two (or three) particles on nearly one
line of sight, taken for one, separated by fitting their images to the view pixels.

:func:`split_merged_particles` refits as two images each particle whose one-image fit
leaves its pixels unexplained, started on its line of sight in front of and behind it
(or side by side, for images that touch in every view), and keeps the split when the
images explain the pixels better, move apart across the views and are not another
particle's image (:func:`_two_images`, :func:`_coincides`). The tests on two fitted
images are shared with the hidden-particle search
(:func:`~plenoptrack.locate.perspective.find_hidden_particles`).
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import warnings

import numpy as np
import pandas as pd

from .._columns import POS_COLUMNS, SIGMA_COLUMNS
from ._assign import _predict_all
from .frame import (_CENTROID_SOLUTION, _FIT_CONTRAST, _FIT_ERROR, _FIT_RADIUS, _HIDDEN,
                     _SPLIT_OF, FrameContext, ParticleState, _fit_views, _member_diameter)
from ._nearby import ImageSpans
from ._regions import member_axes, pair_half_separation
from .bodies import parallax_px
from .settings import CheckSettings
from .triangulate import TriangulationFlag

__all__ = ["split_merged_particles", "split_bar", "split_gain_bar", "split_start_travel",
           "keep_centroids_on_images", "waist_depth_px", "SIDE_BY_SIDE_PARALLAX_PX"]


_MOVED_PX = 1.0
"""An image fit that explains a particle's pixels with its image more than this far
(view pixels) from where the particle's solution puts it, in some view, replaces that
solution (:func:`split_merged_particles`): ten times the largest disagreement between
the two on isolated particles (0.07-0.09 px, `small` camera, 0.4 and 2 mm)."""


def split_merged_particles(ctx: FrameContext, state: ParticleState,
                           settings: CheckSettings, *,
                           only: np.ndarray | None = None) -> ParticleState:
    """Stage 5c: separate two particles on nearly one line of sight taken for one.

    Two particles whose images overlap in every view (nearly in line with the camera,
    far enough apart in depth) give one merged region per view; the clustering takes
    them for one particle between them, and the refinement cannot explain its pixels
    with one disc (``UNEXPLAINED``); when no neighbour overlaps the pair, the refinement
    never fits it at all. Each particle whose last image fit left more than
    ``settings.split_max_model_error`` of the background unexplained (a lower bar than
    ``refine_max_model_error``, above which the refinement gives a particle back its
    centroid solution: a pair whose images merge in every view can be fitted by one disc
    almost well enough), or that was never fitted, is refitted as two (a never fitted
    one only once a one-image fit has left more than that unexplained)
    (:func:`~plenoptrack.locate.refine.fit_images`, its neighbours held), started on the
    line of sight of its central-view image one view pixel of image travel in front of
    it and behind it (:func:`_line_of_sight_pair`); a fit that runs off from there is
    tried once more from a third of the image radius of travel
    (:func:`split_start_travel`). A single image whose line-of-sight pair fails is also
    tried as two images side by side, started along its whole regions' major axis as two
    discs with the regions' second moments, when those would have a waist a view pixel
    deep between them (:func:`_lateral_pair`): particles whose images touch in every
    view, which the segmentation takes apart only when the frame's typical region is a
    single image. The two are kept when both images are opaque enough
    (``settings.split_min_contrast``), the fit explains the pixels better (model error
    at most ``1 / settings.split_min_gain`` of the single fit's, or, on the
    pair's own pixels, a mean-square residual lower than the single image's by at least
    :func:`split_gain_bar`: images of particles never located add to both alike, and
    cancel in the difference but not in the ratio), their
    images move apart across the views by at least one view pixel and either stand apart
    by the smaller radius in some view or are two bodies apart in space
    (:func:`_apart_in_space`; only parallax tells two particles from one elongated
    image), or by half a view pixel where they explain the pixels, stand side by side in
    every view and are two bodies apart in space (:func:`_two_images`), and neither is a
    particle already located whose pixels are explained (an unexplained one at most
    twice the size of the split's images can be the merged image of a particle of the
    group and another). When no pair passes, or the best pair still
    leaves the pixels unexplained (model error above
    ``settings.split_max_model_error``), three images are tried under the same tests,
    started at the pair's starts and the image itself: a pair cannot explain three
    particles whose images all merge and can settle between them with one faint image.
    An image a fit drives to nothing is dropped and the images left are refitted, kept
    when they explain the pixels and stay on the line of sight (:func:`_without_vanished`).
    While the group still leaves the pixels unexplained, one of its images is split
    again under the same tests, up to ``settings.split_max_images`` images. The image
    nearer the merged solution in depth takes the particle's row, the others are
    appended; all carry ``REFINED`` and ``SPLIT`` and their position, sigma and image
    radius come from the fit. The unexplained neighbours of a split particle
    are then refitted beside the group and become ``REFINED`` where that explains their
    pixels; one that stays unexplained and is one with an image of the group
    (:func:`_coincides`) is dropped, the group's image taking its place.

    Where no split passes, a particle whose regions are elongated (:data:`END_FIT_ASPECT`)
    is fitted as one image from either end of them as well, and takes the better end's
    image where it explains the pixels better (:meth:`_SplitRun.fit_from_ends`: out of
    focus a pin's head and stem merge into one region, whose centred disc lies on
    neither).
    Where no split passes but one image explains the pixels (model error at most
    ``settings.refine_max_model_error``, refitted on every view), that image replaces
    the particle's solution in two cases: a particle found in the residual
    (:func:`~plenoptrack.locate.perspective.find_hidden_particles`) whose refit beside
    neighbours that have since been split or refitted left it unexplained; and a particle
    whose centroids scatter by more than :data:`_MOVED_PX` about its solution when the image lies
    more than that from the solution's in some view and on at least a quarter of its centroids
    (regions merged with a neighbour's image in the other views pulled the solution away; on the
    `small` camera's sparse 2 mm particles the true particle's fit lay on 49-58 % of
    them, a spurious cluster's in a crowd on 1-2 %); such a particle keeps only the
    centroids within ``ctx.tolerance_px`` of its image (its ``n_views`` and
    ``residual_px`` theirs). The unexplained neighbours of a particle moved are refitted
    beside it in turn.
    """
    if _FIT_ERROR not in state.table.columns or state.n_particles == 0:
        return state
    candidates = _candidates(state, settings, only)
    if len(candidates) == 0:
        return state
    run = _SplitRun(ctx, state, settings)
    for m in candidates:
        run.try_particle(m)
    return run.finished()


_UNEXPLAINED = int(TriangulationFlag.UNEXPLAINED)
_REFINED = int(TriangulationFlag.REFINED)
_SPLIT = int(TriangulationFlag.SPLIT)


def _never_fitted(flags: np.ndarray, fit_error: np.ndarray) -> np.ndarray:
    """(P,) bool: the particles no image fit has explained or tried (no neighbour
    overlaps them), from their ``flags`` and last image fit's model error."""
    return ((flags & (_UNEXPLAINED | _REFINED)) == 0) & ~np.isfinite(fit_error)


def _candidates(state: ParticleState, settings: CheckSettings,
                only: np.ndarray | None) -> np.ndarray:
    """The particles :func:`split_merged_particles` tries: those the refinement could not
    explain (model error above :func:`split_bar`), and those it never fitted (no
    neighbour overlaps them; a one-image fit must fail first); not split yet, among
    ``only``, with a position. Whether two images slide over each other is decided on
    the fit (their parallax, :func:`_two_images`), not on the regions: a pair whose
    images merge in every view can keep its regions' length across the views."""
    flags = state.table["flags"].fillna(0).to_numpy(np.int64)
    error = state.table[_FIT_ERROR].to_numpy(float)
    return np.flatnonzero(((np.isfinite(error) & (error > split_bar(error, settings)))
                           | _never_fitted(flags, error))
                          & ((flags & _SPLIT) == 0)
                          & (True if only is None else np.asarray(only, dtype=bool))
                          & np.all(np.isfinite(state.positions), axis=1))


class _SplitRun:
    """The working arrays of one :func:`split_merged_particles` call and its steps.

    Rows ``0..P-1`` are the state's particles; each kept split appends its other images
    as rows (``parent`` holds the particle each came from). Positions, sigma, image
    radius and contrast, flags and model errors are updated in place as particles are
    split or refitted, and their images (``pred``, ``spans``) with them, so that every
    later fit is made beside the neighbours as they now stand.
    """

    def __init__(self, ctx: FrameContext, state: ParticleState, settings: CheckSettings):
        self.ctx, self.state, self.settings = ctx, state, settings
        table = state.table
        self.flags = table["flags"].fillna(0).to_numpy(np.int64).copy()
        self.pos = state.positions.copy()
        self.single_error = table[_FIT_ERROR].to_numpy(float).copy()
        self.never_fitted = _never_fitted(self.flags, self.single_error)
        self.split_max = split_bar(self.single_error, settings)
        self.gain_bar = split_gain_bar(self.single_error, settings)
        self.views_uv, self.view_rc = _fit_views(ctx)
        # neighbours are drawn with the image their own fit found, where they had one
        self.fit_radius = table[_FIT_RADIUS].to_numpy(float)
        self.radius = np.where(np.isfinite(self.fit_radius), self.fit_radius,
                               0.5 * _member_diameter(ctx.detections, state.owner,
                                                      state.n_particles))
        self.contrast = np.nan_to_num(table[_FIT_CONTRAST].to_numpy(float), nan=0.9)
        self.sigma = table[list(SIGMA_COLUMNS)].to_numpy(float).copy()
        self.parent, self.n_views = [], []          # of each appended particle
        self.pred = _predict_all(ctx.dlfc, self.pos, self.views_uv)   # kept current
        self.spans = ImageSpans(self.pred)                             # and where they lie
        self.group_error = []              # (particle, model error of its split group)
        self.refitted_rows = set()         # particles given a one-image fit here
        self.relocated_rows = set()        # and those of them its image put elsewhere
        # centroids that scatter by more than _MOVED_PX about their solution: regions of
        # other particles' images among them
        self.scattered = table["residual_px"].to_numpy(float) > _MOVED_PX
        self.hidden = (table[_HIDDEN].fillna(False).to_numpy(bool) if _HIDDEN in table.columns
                       else np.zeros(len(table), dtype=bool))
        self.axes = member_axes(ctx.detections, state.owner, state.n_particles,
                                ctx.detections["whole"].to_numpy(bool))[:, :3]
        # the decision's fits use a sub-grid of the views; a split that passes is refitted
        trial = _view_subgrid(self.view_rc, settings.split_trial_stride)
        self.trial_uv, self.trial_rc = self.views_uv[trial], self.view_rc[trial]
        self.all_views = bool(trial.all())

    def fit(self, views_uv, view_rc, xyz, rc, held, **kw):
        """Images at ``xyz`` (k, 3) with radius and contrast ``rc`` (k, 2) fitted to the
        pixels of the given views beside the ``held`` particles as they now stand
        (:meth:`~plenoptrack.locate.frame.FrameContext.fit_images`)."""
        return self.ctx.fit_images((views_uv, view_rc), xyz, rc, self.pos[held],
                                   np.c_[self.radius[held], self.contrast[held]], **kw)

    def neighbours(self, i, pred) -> np.ndarray:
        """Particles whose images come within 4 view pixels of particle i's in a view."""
        live = np.all(np.isfinite(self.pos), axis=1) & np.isfinite(self.radius)
        near = live & self.spans.meet(pred, pred[i], self.radius + self.radius[i] + 4.0)
        near[i] = False
        return np.flatnonzero(near)

    def moved(self, m, params) -> bool:
        """Whether the image of ``params`` (1, 5) lies more than :data:`_MOVED_PX` from
        particle ``m``'s in some view."""
        offset = self.pred[m] - _predict_all(self.ctx.dlfc, params[:, :3], self.views_uv)[0]
        return bool(np.nanmax(np.hypot(*offset.T), initial=0.0) > _MOVED_PX)

    def relocated(self, m, params) -> bool:
        """Whether the one image ``params`` (1, 5) that explains particle ``m``'s pixels
        puts it elsewhere: its centroids scatter by more than :data:`_MOVED_PX` about
        their solution, the image lies more than that from the particle's in some view,
        and at least a quarter of the centroids lie within ``ctx.tolerance_px`` of the
        image (the particle's own; the rest were regions merged with another particle's
        image that pulled the solution away)."""
        if not (self.scattered[m] and self.moved(m, params)):
            return False
        _, off = _centroid_offsets(self.ctx, self.state.owner, m, params[0, :3])
        return bool(np.mean(off <= self.ctx.tolerance_px) >= 0.25) if len(off) else False

    def set_image(self, m, params, sigma) -> None:
        """Particle ``m`` takes the fitted image ``params`` (5,) and its ``sigma`` (3,)
        (kept where the fit gave none), and its images follow."""
        self.pos[m] = params[:3]
        self.sigma[m] = np.where(np.isfinite(sigma), sigma, self.sigma[m])
        self.radius[m], self.contrast[m] = params[3:]
        self.flags[m] = (self.flags[m] & ~_UNEXPLAINED) | _REFINED
        self.pred[m] = _predict_all(self.ctx.dlfc, self.pos[[m]], self.views_uv)[0]
        self.spans.set_rows([m], self.pred[[m]])

    def explain_alone(self, m, params) -> bool:
        """Refit particle ``m`` as one image from ``params`` (1, 5) on every view beside
        its neighbours; where it explains the pixels it replaces the particle's position
        and image, clears its unexplained flag and returns True. A particle moved by more
        than :data:`_MOVED_PX` had its image drawn in the wrong place beside its
        neighbours: those left unexplained are refitted beside it in turn."""
        fit = self.fit(self.views_uv, self.view_rc, params[:, :3], params[:, 3:],
                       self.neighbours(m, self.pred),
                       max_depth_shift=0.1 * self.ctx.volume_depth_mm)
        if (fit is None or not np.all(np.isfinite(fit.params))
                or not fit.model_error <= self.settings.refine_max_model_error):
            return False
        self.single_error[m] = fit.model_error
        self.refitted_rows.add(m)
        was_moved = self.moved(m, fit.params)
        self.set_image(m, fit.params[0], fit.sigma[0])
        if was_moved:
            for q in self.neighbours(m, self.pred):
                if self.flags[q] & _UNEXPLAINED:
                    self.explain_alone(q, np.array([[*self.pos[q], self.radius[q],
                                                     self.contrast[q]]]))
        return True

    def distinct(self, fit, m) -> bool:
        """Whether the fit shows ``k`` opaque particles where m was, each two apart by
        their parallax, none of them one already located whose pixels are explained."""
        if (fit is None or not np.all(np.isfinite(fit.params))
                or fit.params[:, 4].min() < self.settings.split_min_contrast):
            return False
        explained = bool(fit.model_error <= self.split_max)
        group_pred = _predict_all(self.ctx.dlfc, fit.params[:, :3], self.views_uv)   # (k, V, 2)
        for a, b in itertools.combinations(range(len(fit.params)), 2):
            if not _two_images(self.ctx.dlfc, fit.params[[a, b]], group_pred[[a, b]],
                               explained=explained):
                return False
        # An unexplained particle can be a merged image the split is taking apart, one
        # at most twice the size of the split's images; a larger one is a particle
        # whose image a small disc of the split would only nibble at.
        merged_image = (((self.flags & _UNEXPLAINED) > 0)
                        & (self.radius <= 2.0 * fit.params[:, 3].max()))
        others = np.setdiff1d(np.flatnonzero(np.isfinite(self.radius)
                                             & np.all(np.isfinite(self.pos), axis=1)
                                             & ~merged_image), [m])
        return not _coincides(group_pred, fit.params[:, 3], self.pred[others],
                              self.radius[others], self.spans.subset(others))

    def trial_fit(self, params, held, reference):
        """Images ``params`` (k, 5) fitted on the trial views beside ``held``."""
        return self.fit(self.trial_uv, self.trial_rc, params[:, :3], params[:, 3:], held,
                        max_depth_shift=self.ctx.volume_depth_mm, reference=reference)

    def better(self, fit, best, m, error) -> bool:
        """Whether ``fit`` explains the pixels better than a reference of model error
        ``error`` (:func:`_explains_more`), has a lower model error than ``best`` and
        passes :meth:`distinct`."""
        return bool(fit is not None
                    and _explains_more(fit, error, self.settings, self.gain_bar)
                    and (best is None or fit.model_error < best.model_error)
                    and self.distinct(fit, m))

    def best_replacement(self, m, held, start, error, reference, n, lateral=None):
        """The best fit on the trial views of ``start`` (k, 5) with one image replaced
        by ``n`` (2: the line-of-sight pair of :func:`_line_of_sight_pair`; 3: the pair
        and the image itself) that explains the pixels better than the ``reference``
        model with model error ``error`` (:func:`_explains_more`) and passes
        :meth:`distinct`; None if no replacement does. A single image whose
        line-of-sight pair fails is tried as the ``lateral`` pair (2, 5) too, when
        given."""
        dlfc = self.ctx.dlfc
        fit_trial = functools.partial(self.trial_fit, held=held, reference=reference)

        best = None
        for j in range(len(start)):
            rc = np.vstack([np.delete(start[:, 3:], j, axis=0),
                            np.tile([start[j, 3], 0.9], (n, 1))])
            # one view pixel of travel apart first; a fit that runs off from there is
            # tried once more from a start a third of the image radius apart
            for travel in dict.fromkeys((1.0, split_start_travel(start[j, 3]))):
                pair = _line_of_sight_pair(dlfc, start[j, :3], self.views_uv, travel)
                xyz = np.vstack([np.delete(start[:, :3], j, axis=0),
                                 pair if n == 2 else [pair[0], start[j, :3], pair[1]]])
                fit = fit_trial(np.c_[xyz, rc])
                if fit is not None:
                    break
            fit = _without_vanished(fit, start, j, dlfc, self.split_max, fit_trial)
            kept = self.better(fit, best, m, error)
            if not kept and lateral is not None and n == 2 and len(start) == 1:
                # two images side by side, merged in every view: their regions are
                # elongated, and a pair on the line of sight does not reach them
                fit = _without_vanished(fit_trial(lateral), start, j, dlfc, self.split_max,
                                        fit_trial)
                kept = self.better(fit, best, m, error)
            if kept:
                best = fit
        return best

    def split(self, m, held, start, error, reference, lateral=None):
        """The best fit of one more image than ``start`` (k, 5) on the trial views, each
        image in turn replaced by a pair on its line of sight, when it explains the
        pixels better than the ``reference`` model (k, 5) with model error ``error`` on
        the trial views (:func:`_explains_more`) and passes :meth:`distinct`; or of two
        more images, when they explain the pixels better than that pair (or the
        reference, without one): ``(fit refitted on every view, its model error on the
        trial views)``; else None."""
        best = self.best_replacement(m, held, start, error, reference, 2, lateral)
        # Three particles whose images all merge: a pair cannot explain them, and the
        # pair's fit can settle between them with one faint image. Each image replaced
        # by three on its line of sight (itself and the pair's starts) finds them.
        if (len(start) + 2 <= self.settings.split_max_images
                and (best is None or best.model_error > self.split_max)):
            more = self.best_replacement(m, held, start,
                                         *((error, reference) if best is None
                                           else (best.model_error, best.params)), 3)
            best = best if more is None else more
        if best is None:
            return None
        trial_error = best.model_error     # the group on every view, from the trial's fit
        # measured on every view, with the blurred union of two images that run together
        # (the product decided that they are two: :mod:`~plenoptrack.locate.refine`)
        best = self.fit(self.views_uv, self.view_rc, best.params[:, :3], best.params[:, 3:],
                        held, max_depth_shift=self.ctx.volume_depth_mm, union=True)
        return (best, trial_error) if self.distinct(best, m) else None

    def try_particle(self, m) -> None:
        """Fit particle ``m`` as one image and as two or more; keep a split that passes
        (:meth:`take_group`), or, with none, the one image where it explains the pixels
        and the refinement could not (a particle found in the residual) or the centroids
        put the particle elsewhere (:meth:`relocated`)."""
        if not self.never_fitted[m] and not self.single_error[m] > self.split_max:
            return                         # explained beside a neighbour's split meanwhile
        if not np.all(np.isfinite(self.pos[m])):
            return                         # taken over by a neighbour's split meanwhile
        held = self.neighbours(m, self.pred)
        # one image and two, fitted to the same pixels
        start = np.array([[*self.pos[m], self.radius[m], 0.9]])
        reference = None                   # a fitted single image, when there is one
        if self.never_fitted[m] or not self.all_views:
            # no limit on its depth: only its model error is used, and one image that
            # wanders off in depth is one that does not explain the pixels
            one = self.fit(self.trial_uv, self.trial_rc, self.pos[[m]],
                           np.array([[self.radius[m], 0.9]]), held)
            if one is None or not np.isfinite(one.model_error):
                return
            if self.never_fitted[m] and one.model_error <= self.split_max:
                if self.relocated(m, one.params) and self.explain_alone(m, one.params):
                    self.relocated_rows.add(m)
                return                     # one image explains it: left as it is
            self.single_error[m] = one.model_error
            reference = one.params
        lateral = _lateral_pair(self.ctx.dlfc, self.pos[m], self.axes[m])
        found = self.split(m, held, start, self.single_error[m], reference, lateral)
        # Three or more particles on one line of sight: split an image of the group
        # again while the group leaves the pixels unexplained.
        while (found is not None and len(found[0].params) < self.settings.split_max_images
               and found[0].model_error > self.split_max):
            more = self.split(m, held, found[0].params, found[1], found[0].params)
            if more is None:
                break
            found = more
        if found is None and reference is not None and self.fit_from_ends(m, held, one):
            return
        alone = (found is None and reference is not None
                 and self.single_error[m] <= self.settings.refine_max_model_error)
        put_back = alone and self.relocated(m, reference)
        if alone and (self.flags[m] & _UNEXPLAINED and self.hidden[m] or put_back):
            # No split, but one image explains the pixels: where the refinement's fit of
            # a particle found in the residual could not (a neighbour it was fitted
            # beside has since been split or refitted), or where the centroids put the
            # particle elsewhere (its regions were merged with a neighbour's in some
            # views), that image replaces them.
            if self.explain_alone(m, reference) and put_back:
                self.relocated_rows.add(m)
            return
        if found is None or not np.all(np.isfinite(found[0].sigma)):
            return                         # no split, or one the pixels do not determine
        self.take_group(m, found[0], held)

    def fit_from_ends(self, m, held, one) -> bool:
        """Particle ``m``'s image fitted from either end of its elongated regions; True
        when that image is kept.

        One disc fitted to an elongated image from its centroid stays at its centre:
        out of focus a pin's head merges with its stem into one region, and the disc
        lies between the two, neither on the head nor explaining the stem. Fitted from
        the ends of the regions' long axis as well (:func:`_end_starts`; on the trial
        views, beside the same neighbours as the centred fit ``one``), the disc finds the
        darker end; a symmetric image (an ellipsoid) keeps it at its centre. The best end
        is kept when it explains the pixels better than the centred fit by
        ``check.refine_max_model_error**2`` in mean square (the test a particle found in
        the residual passes) and its refit on every view stays within a tenth of the
        volume depth; the particle then takes that image, and stays ``UNEXPLAINED``
        where it leaves more than ``check.refine_max_model_error`` (the rest of the
        body: a search of the residual divides it out with the regions' ellipse,
        :func:`~plenoptrack.locate.hidden._elongated_silhouettes`)."""
        starts = _end_starts(self.ctx.dlfc, self.pos[m], self.axes[m])
        if starts is None:
            return False
        best = one
        for start in starts:
            fit = self.fit(self.trial_uv, self.trial_rc, start[None, :3], start[None, 3:], held)
            if (fit is not None and np.all(np.isfinite(fit.params))
                    and fit.model_error < best.model_error):
                best = fit
        bar = self.settings.refine_max_model_error
        if best is one or one.model_error ** 2 - best.model_error ** 2 < bar ** 2:
            return False
        fit = self.fit(self.views_uv, self.view_rc, best.params[:, :3], best.params[:, 3:],
                       held, max_depth_shift=0.1 * self.ctx.volume_depth_mm)
        if (fit is None or not np.all(np.isfinite(fit.params))
                or not np.all(np.isfinite(fit.sigma))):
            return False
        self.single_error[m] = fit.model_error
        self.refitted_rows.add(m)
        self.set_image(m, fit.params[0], fit.sigma[0])
        if fit.model_error > bar:
            self.flags[m] |= _UNEXPLAINED
        return True

    def take_group(self, m, group, held) -> None:
        """Particle ``m`` becomes the split ``group``: the image nearer its solution in
        depth keeps its row, the others are appended; then its neighbours the refinement
        could not explain are refitted beside the group, and one still unexplained that
        is one with an image of the group is dropped (the group's image takes its
        place)."""
        self.group_error.append((m, group.model_error))
        k = len(group.params)
        first = int(np.argmin(np.abs(group.params[:, 2] - self.pos[m, 2])))
        rest = [i for i in range(k) if i != first]
        self.pos = np.vstack([self.pos, group.params[rest, :3]])
        self.pos[m] = group.params[first, :3]
        self.sigma = np.vstack([self.sigma, group.sigma[rest]])
        self.sigma[m] = group.sigma[first]
        self.radius = np.append(self.radius, group.params[rest, 3])
        self.radius[m] = group.params[first, 3]
        self.contrast = np.append(self.contrast, group.params[rest, 4])
        self.contrast[m] = group.params[first, 4]
        self.flags[m] = (self.flags[m] & ~_UNEXPLAINED) | _REFINED | _SPLIT
        self.flags = np.append(self.flags, np.full(k - 1, _REFINED | _SPLIT))
        self.parent.extend([m] * (k - 1))
        self.n_views.extend([group.n_views] * (k - 1))
        # The group's merged image also spoilt its neighbours' fits: refit those the
        # refinement could not explain, now beside the group.
        self.pred = _predict_all(self.ctx.dlfc, self.pos, self.views_uv)
        self.spans = ImageSpans(self.pred)
        n_error = len(self.single_error)
        held_error = np.where(held < n_error,
                              self.single_error[np.minimum(held, n_error - 1)], np.nan)
        rows = np.r_[m, np.arange(len(self.pos) - (k - 1), len(self.pos))]   # the group's
        refitted, errors = [], [group.model_error]
        for q in held[((self.flags[held] & _UNEXPLAINED) > 0) | (held_error > self.split_max)]:
            one = self.fit(self.views_uv, self.view_rc, self.pos[[q]],
                           np.array([[self.radius[q], self.contrast[q]]]),
                           self.neighbours(q, self.pred),
                           max_depth_shift=0.1 * self.ctx.volume_depth_mm)
            if one is None or not np.all(np.isfinite(one.params)):
                continue
            self.single_error[q] = one.model_error
            if one.model_error <= self.settings.refine_max_model_error:
                self.set_image(q, one.params[0], one.sigma[0])
                refitted.append(int(q))
                errors.append(one.model_error)
        # Fitted one after another, the group beside the neighbour's old image and the
        # neighbour beside the group's new one, images that merge in every view pull each
        # other apart in depth: fit those together once more.
        merged = [q for q in refitted if any(
            _merged_in_every_view(self.pred[q], self.pred[g], self.radius[q] + self.radius[g])
            for g in rows)]
        if merged:
            self.polish(np.r_[rows, merged], min(errors))
        # One that is still unexplained and one with an image of the group was a merged
        # image the group took apart: the group's image replaces it.
        for q in held[(self.flags[held] & _UNEXPLAINED) > 0]:
            if _coincides(self.pred[rows], self.radius[rows], self.pred[[q]],
                          self.radius[[q]]):
                self.pos[q] = self.radius[q] = self.pred[q] = np.nan
                self.spans.set_rows([q], self.pred[[q]])

    def polish(self, free, bar) -> None:
        """Fit the particles ``free`` (a split group and the neighbours refitted beside
        it whose images merge with the group's in every view) again together, their
        other neighbours held. Where the joint fit explains the pixels
        (``check.refine_max_model_error``) at least as well as the best of the separate
        fits (model error at most ``bar``) and moves no image sideways by more than half
        its radius in the central view, each particle takes its image from it. Fitted one
        after another, each was drawn beside the others' images as they stood before its
        own fit; on the accuracy matrix's development seeds (`small`, realistic optics,
        1 mm spheres) the split half of a line-of-sight pair then lay 1.5-2.5 mm off in
        depth and 0.84 of its diameter, and the joint fit put it within 0.7 mm."""
        near = np.zeros(len(self.pos), dtype=bool)
        for q in free:
            near[self.neighbours(q, self.pred)] = True
        near[free] = False
        joint = self.fit(self.views_uv, self.view_rc, self.pos[free],
                         np.c_[self.radius[free], self.contrast[free]], np.flatnonzero(near),
                         max_depth_shift=self.ctx.volume_depth_mm, union=True)
        if (joint is None or not np.all(np.isfinite(joint.params))
                or joint.model_error > min(bar, self.settings.refine_max_model_error)):
            return
        # a joint fit that took a particle sideways has drawn it over another's image
        dlfc = self.ctx.dlfc
        before = np.column_stack(dlfc.predict(*self.pos[free].T, 0.0, 0.0))
        after = np.column_stack(dlfc.predict(*joint.params[:, :3].T, 0.0, 0.0))
        if np.any(np.hypot(*(after - before).T) > 0.5 * self.radius[free]):
            return
        for i, q in enumerate(free):
            self.set_image(q, joint.params[i], joint.sigma[i])

    def finished(self) -> ParticleState:
        """The state with the splits and refits made: appended rows for the split
        images, flags, positions, sigma, images and model errors updated."""
        state, table = self.state, self.state.table
        flags, pos, sigma = self.flags, self.pos, self.sigma
        # A particle never fitted before, whose one-image fit here left its pixels
        # unexplained and which no split took apart, is unexplained like those the
        # refinement could not explain (flagged only now: the tests above decided on the
        # flags the refinement left).
        n = state.n_particles
        left = (self.never_fitted & (self.single_error > self.settings.refine_max_model_error)
                & np.all(np.isfinite(pos[:n]), axis=1)
                & ((flags[:n] & _SPLIT) == 0))
        flags[np.flatnonzero(left)] |= _UNEXPLAINED
        # A particle put back by its image keeps only the centroids on that image: the
        # others were regions merged with a neighbour's, and its scatter (residual_px,
        # n_views, hence chi2 and the frame's typical scatter) is that of the centroids
        # it keeps.
        owner, table = keep_centroids_on_images(self.ctx, state.owner, table,
                                                sorted(self.relocated_rows), pos)
        if not self.parent:
            table = table.copy()
            table["flags"] = flags
            table[_FIT_ERROR] = self.single_error
            table[list(POS_COLUMNS)] = pos
            table[list(SIGMA_COLUMNS)] = sigma
            refitted = np.isin(np.arange(len(pos)), list(self.refitted_rows))
            table[_FIT_RADIUS] = np.where(refitted, self.radius, self.fit_radius)
            table[_FIT_CONTRAST] = np.where(refitted, self.contrast, table[_FIT_CONTRAST])
            return dataclasses.replace(state, owner=owner, positions=pos, table=table)
        extra = table.loc[self.parent].copy()
        extra["cluster"] = -1
        extra[_SPLIT_OF] = self.parent     # the halves own no centroids: their pair's are these
        extra["n_views"] = np.asarray(self.n_views, dtype=extra["n_views"].dtype)
        # residual_px stays the merged pair's: its excess scatter sizes both halves' sigma
        table = pd.concat([table, extra], ignore_index=True)
        table["flags"] = flags
        table[list(POS_COLUMNS)] = pos
        table[list(SIGMA_COLUMNS)] = sigma
        table[_FIT_RADIUS] = self.radius
        table[_FIT_CONTRAST] = self.contrast
        # how well each particle's last fit explains its pixels: a split group's own error
        fit_error = np.append(self.single_error, np.full(len(self.parent), np.nan))
        parent = np.asarray(self.parent)
        for m, error in self.group_error:
            fit_error[m] = error
            fit_error[state.n_particles + np.flatnonzero(parent == m)] = error
        table[_FIT_ERROR] = fit_error
        initial = np.vstack([state.initial, pos[len(state.initial):]])
        return dataclasses.replace(state, owner=owner, initial=initial, positions=pos,
                                   table=table)

def split_bar(fit_error: np.ndarray, settings: CheckSettings) -> float:
    """The model error above which a particle is tried as a split: the larger of
    ``settings.split_max_model_error`` and ``settings.split_floor_ratio`` times the
    frame's median image-fit model error (NaN entries, particles not fitted, left out),
    but never above ``settings.refine_max_model_error``: a particle the refinement could
    not explain is always tried.

    One disc never explains an image exactly (the edge profile, the background, the
    neighbours held at their own fits): the frame's median fit says how far from exact
    its explained images typically are, which differs from camera to camera (about 0.04
    of the background on the ``small`` camera with realistic optics, 0.05 on hall2019).
    A merged pair must stand out from that, not from a fixed figure."""
    floor = _typical_fit_error(fit_error)
    bar = max(settings.split_max_model_error, settings.split_floor_ratio * floor)
    return min(bar, max(settings.refine_max_model_error, settings.split_max_model_error))


def split_gain_bar(fit_error: np.ndarray, settings: CheckSettings) -> float:
    """The fall in mean-square model error (fraction of the background, squared) by
    which more images must explain a split candidate's own pixels better than the model
    they split, unless they pass the ratio ``settings.split_min_gain``: what sets a
    candidate apart from the frame's typical explained image, ``bar**2 - typical**2``,
    with ``bar`` :func:`split_bar` and ``typical`` the frame's median image-fit model
    error (NaN entries left out), at most ``bar / max(split_floor_ratio, 1)``. With
    ``settings.split_floor_ratio`` 0 (the fixed bar alone) it is ``bar**2``.

    In a frame where no image was fitted (the refinement fits only images that overlap;
    a sparse frame may have none) the typical error is unknown and is taken as that
    largest value, the one the fixed bar stands for (0.042 of the background with the
    defaults; about what an explained image leaves on the `small` camera with realistic
    optics). Taken as 0, the full ``bar**2``, it turned away pairs that the split had
    found: in the mixed 0.2-2 mm cell of the accuracy matrix (development seeds), a 0.4
    or 0.5 mm particle partly hidden by a 1.4 or 1.6 mm one was fitted within 0.01 mm
    laterally (0.3-0.6 mm in depth) with model errors falling from 0.062 to 0.043 and
    from 0.056 to 0.038, and only the large particle was reported.

    A pair whose images merge in every view, fitted as one disc, leaves a little more
    than the bar unexplained; fitted as two, about as little as a typical image. Asking
    the pair to remove ``bar**2`` itself asked it to explain more than ever set the
    particle apart: on hall2019 (1000 particles of 0.5 mm, ideal optics, median model
    error 0.050, bar 0.060) a pair 0.16 mm apart laterally and 1.5 mm in depth was
    fitted within 0.07 mm of both particles (model error 0.065 to 0.045 on its pixels)
    and rejected, and the locator reported one particle midway between them, 0.7 mm
    off, with sigma_z 0.06 mm."""
    bar = split_bar(fit_error, settings)
    if settings.split_floor_ratio == 0:
        return bar ** 2
    cap = bar / max(settings.split_floor_ratio, 1.0)
    if not np.isfinite(np.asarray(fit_error, dtype=float)).any():
        return bar ** 2 - cap ** 2         # no image fitted: the typical error unknown
    return bar ** 2 - min(_typical_fit_error(fit_error), cap) ** 2


def _typical_fit_error(fit_error: np.ndarray) -> float:
    """The frame's median image-fit model error (NaN entries, particles not fitted, left
    out); 0 when none was fitted."""
    fitted = np.asarray(fit_error, dtype=float)
    fitted = fitted[np.isfinite(fitted)]
    return float(np.median(fitted)) if len(fitted) else 0.0


def _view_subgrid(view_rc: np.ndarray, stride: int, *, min_views: int = 12) -> np.ndarray:
    """(V,) bool: the views whose ``(v, u)`` index ``view_rc`` (V, 2) differs from the
    central view's by a multiple of ``stride`` in both, a regular sub-grid spanning the
    aperture; every view when that leaves fewer than ``min_views``."""
    centre = np.round(np.median(view_rc, axis=0)).astype(np.int64)
    keep = np.all((view_rc - centre) % stride == 0, axis=1)
    return keep if keep.sum() >= min_views else np.ones(len(view_rc), dtype=bool)


def _line_of_sight_pair(dlfc, xyz: np.ndarray, views_uv: np.ndarray,
                        travel_px: float = 1.0) -> np.ndarray:
    """(2, 3) starting positions of a split: the points of the line of sight through
    ``xyz`` (mm) of its central-view image ``(u, v) = (0, 0)`` whose images move
    ``travel_px`` view pixels (:func:`~plenoptrack.locate.uncertainty.image_travel_px`)
    nearer to and farther from those of ``xyz`` over the views, in front of it and
    behind it."""
    _, jac = dlfc.predict_with_jacobian(xyz[0], xyz[1], xyz[2], views_uv[:, 0], views_uv[:, 1])
    rate = np.sqrt(8.0 * np.sum(np.var(jac[:, :, 2], axis=0)))       # travel, px per mm
    dz = travel_px / max(rate, 1e-6)
    s0, t0 = dlfc.predict(xyz[0], xyz[1], xyz[2], 0.0, 0.0)
    out = np.empty((2, 3))
    for i, z in enumerate((xyz[2] - dz, xyz[2] + dz)):
        q = np.array([xyz[0], xyz[1], z], dtype=float)
        for _ in range(4):   # Newton: the same central-view image at depth z
            st, j = dlfc.predict_with_jacobian(q[0], q[1], q[2], 0.0, 0.0)
            q[:2] += np.linalg.solve(j[:, :2], [s0 - st[0], t0 - st[1]])
        out[i] = q
    return out


def _lateral_pair(dlfc, xyz: np.ndarray, axes: np.ndarray) -> np.ndarray | None:
    """(2, 5) starting images ``(x, y, z, r, c)`` of a split of an image elongated by two
    discs side by side: two discs of the regions' minor radius whose union has the
    regions' second moments (:func:`~plenoptrack.locate._regions.pair_half_separation`,
    as the segmentation's pair split places them), along the major axis
    in the central view, at the merged depth; None for a particle without regions or
    one whose two such discs would have no waist a view pixel deep between them
    (:func:`waist_depth_px`; the split keeps side by side only images with one)."""
    major, minor, angle = axes
    if not np.all(np.isfinite(axes)) or major <= minor:
        return None
    half = float(pair_half_separation(major, minor))
    if waist_depth_px(2.0 * half, 0.5 * minor, 0.5 * minor) < 1.0:
        return None
    return np.c_[_along_major_axis(dlfc, xyz, angle, half), np.full(2, 0.5 * minor),
                 np.full(2, 0.9)]


def _along_major_axis(dlfc, xyz: np.ndarray, angle: float, distance_px: float) -> np.ndarray:
    """(2, 3) positions (mm) at the depth of ``xyz`` whose central-view images lie
    ``distance_px`` view pixels either side of its own along the direction ``angle``
    (radians from ``s`` toward ``t``)."""
    s0, t0 = dlfc.predict(xyz[0], xyz[1], xyz[2], 0.0, 0.0)
    out = np.empty((2, 3))
    for i, sign in enumerate((-1.0, 1.0)):
        target = np.array([s0, t0]) + sign * distance_px * np.array([math.cos(angle),
                                                                     math.sin(angle)])
        q = np.array(xyz, dtype=float)
        for _ in range(4):   # Newton: that central-view image at the same depth
            st, j = dlfc.predict_with_jacobian(q[0], q[1], q[2], 0.0, 0.0)
            q[:2] += np.linalg.solve(j[:, :2], target - np.asarray(st, dtype=float))
        out[i] = q
    return out


def _end_starts(dlfc, xyz: np.ndarray, axes: np.ndarray) -> np.ndarray | None:
    """(2, 5) starting images ``(x, y, z, r, c)`` at the two ends of an elongated image:
    discs of the regions' minor radius touching either end of their major axis in the
    central view, at the depth of ``xyz``; None unless the whole regions' median
    ``axes`` (major, minor, angle: :func:`~plenoptrack.locate._regions.member_axes`)
    make an image at least :data:`END_FIT_ASPECT` times as long as wide."""
    major, minor, angle = axes
    if not (np.all(np.isfinite(axes)) and minor > 0 and major >= END_FIT_ASPECT * minor):
        return None
    return np.c_[_along_major_axis(dlfc, xyz, angle, 0.5 * (major - minor)),
                 np.full(2, 0.5 * minor), np.full(2, 0.9)]


END_FIT_ASPECT = 2.5
"""Least ratio of the whole regions' median long axis to their short one for an image to
be fitted from its ends (:func:`_end_starts`, :meth:`_SplitRun.fit_from_ends`). The end
fit is for a compact end on a long thin part (a pin's head on its stem: 3.0-5.5 on the
hall2019 study's images at traverse positions 10, 25 and 40 mm). A shorter, blocky body
has no such end: a disc pulled toward one end of an irregular fragment's image (regions
of aspect 1.5-2.1 on the simulated fragment fields of seeds 0 and 1) comes to rest
between its end and its centre, 0.3-1 mm off the centroid the regions show, and moves
on at every later split pass."""


def split_start_travel(radius_px: float) -> float:
    """Image travel (view pixels) between a split's starting image and each of the two
    it is replaced by, for a second try when the fit from one view pixel ran off: a
    third of the image's radius, at least one view pixel. Two large discs one view pixel
    apart are nearly one disc: the normal equations of their positions, radii and
    contrasts are nearly singular, and the first damped steps go wherever the pixels'
    noise sends them (on 2 mm spheres one image's contrast ran to its bound and its
    position off the volume). Apart by a fixed fraction of their radius, the fit is as
    well conditioned at every image size."""
    return max(1.0, radius_px / 3.0) if np.isfinite(radius_px) else 1.0


def keep_centroids_on_images(ctx: FrameContext, owner: np.ndarray, table: pd.DataFrame,
                             rows, positions: np.ndarray) -> tuple[np.ndarray, pd.DataFrame]:
    """``(owner, table)`` with each particle of ``rows`` keeping only the centroids within
    ``ctx.tolerance_px`` of its image at ``positions[row]`` (mm), the others released
    (owner -1), and its ``n_views`` and ``residual_px`` those of the centroids it keeps:
    for a particle an image fit put back where regions merged with a neighbour's image
    had pulled its centroid solution, which no longer measures it (its recorded
    centroid solution, ``_CENTROID_SOLUTION``, is cleared). The inputs are returned as
    they are when ``rows`` is empty, else copies."""
    if len(rows) == 0:
        return owner, table
    owner, table = owner.copy(), table.copy()
    if _CENTROID_SOLUTION[0] in table.columns:
        table.loc[list(rows), list(_CENTROID_SOLUTION)] = np.nan
    for m in rows:
        mine, off = _centroid_offsets(ctx, owner, m, positions[m])
        on_image = off <= ctx.tolerance_px
        owner[mine[~on_image]] = -1
        table.loc[m, "n_views"] = int(on_image.sum())
        table.loc[m, "residual_px"] = (float(np.sqrt(np.mean(off[on_image] ** 2)))
                                       if on_image.any() else math.nan)
    return owner, table


def _centroid_offsets(ctx: FrameContext, owner: np.ndarray, particle: int,
                      xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The detections ``particle`` owns and their centroids' distances (view pixels)
    from the image of a particle at ``xyz`` (mm) in their views."""
    mine = np.flatnonzero(owner == particle)
    image = _predict_all(ctx.dlfc, np.reshape(xyz, (1, 3)), ctx.views)[0]
    return mine, np.hypot(*(ctx.st[mine] - image[ctx.view[mine]]).T)


def _without_vanished(fit, start: np.ndarray, j: int, dlfc, max_error: float, refit):
    """A split's fit without the images it drove to nothing, where that leaves a split.

    ``fit`` replaced image ``j`` of ``start`` (k, 5) by two or three images on its line of
    sight: its rows are the other images of ``start`` and then the new ones, as
    :func:`split_merged_particles` orders them. An image it drove to the lower bound of
    its radius or contrast (:attr:`~plenoptrack.locate.refine.ImageFit.vanished`) fails
    the split's contrast test and with it the whole fit, though the images left may be the split: a
    pair 4 mm apart in depth that a pair's start ran off from can be found by three images, one of
    which vanishes. When more than ``k`` images are left, ``refit(params)`` fits them again from
    where ``fit`` left them; the refit is returned when it explains the pixels (model error
    at most ``max_error``) and its new images stay on image ``j``'s line of sight (their
    central-view centres within its radius of its own), else ``fit`` unchanged. ``fit``
    may be None.
    """
    if fit is None or not fit.vanished.any() or (~fit.vanished).sum() <= len(start):
        return fit
    again = refit(fit.params[~fit.vanished])
    if again is None or not again.model_error <= max_error:
        return fit
    new = (np.arange(len(fit.params)) >= len(start) - 1)[~fit.vanished]
    centre = np.array(dlfc.predict(*start[j, :3], 0.0, 0.0))
    centres = np.array(dlfc.predict(*again.params[new, :3].T, 0.0, 0.0))
    on_line = np.hypot(*(centres - centre[:, None])) <= start[j, 3]
    return again if on_line.all() else fit


def _coincides(pred: np.ndarray, radius: np.ndarray, other_pred: np.ndarray,
               other_radius: np.ndarray, other_spans: ImageSpans | None = None) -> bool:
    """Whether any of the images ``pred`` (k, V, 2) of radius ``radius`` (k,) is one with
    an image of ``other_pred`` (P, V, 2): centres closer than the larger radius (median
    over the views; the same particle found twice), or overlapping images that keep their
    offset across the views (parallax below one view pixel,
    :func:`~plenoptrack.locate.bodies.parallax_px`): nothing then tells them from one
    elongated image. ``other_spans`` (:class:`~plenoptrack.locate._nearby.ImageSpans` of
    ``other_pred``, computed when not given) rules out the images that never come within
    the sum of the radii, which both tests need."""
    if len(other_pred) == 0:
        return False
    spans = ImageSpans(other_pred) if other_spans is None else other_spans
    return bool(len(_coinciding(pred, radius, other_pred, other_radius, spans)))


def _coinciding(pred: np.ndarray, radius: np.ndarray, other_pred: np.ndarray,
                other_radius: np.ndarray, other_spans: ImageSpans) -> np.ndarray:
    """Rows of ``other_pred`` with an image that one image of ``pred`` coincides with
    (the tests of :func:`_coincides`)."""
    close = np.flatnonzero(other_spans.near(pred, radius[:, None] + other_radius[None]))
    if len(close) == 0:
        return close
    offset = pred[:, None] - other_pred[close][None]                      # (k, p, V, 2)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        dist = np.nanmedian(np.hypot(offset[..., 0], offset[..., 1]), axis=2)
        parallax = parallax_px(offset)
        same = dist < np.maximum(radius[:, None], other_radius[close][None])
        merged = (dist < radius[:, None] + other_radius[close][None]) & (parallax < 1.0)
    return close[np.any(same | merged, axis=0)]


def _explains_more(fit, error: float, settings: CheckSettings, gain_bar: float) -> bool:
    """Whether an image fit with one more image explains the pixels better than the model
    it splits: ``settings.split_min_gain`` times better than ``error``, or, on the fit's
    own pixels against that model (``fit.reference_error``), by a mean square of at
    least ``gain_bar`` (:func:`split_gain_bar`). Images of particles never located add
    to both costs alike: they cancel in the difference, not in the ratio."""
    if fit.model_error * settings.split_min_gain <= error:
        return True
    return bool(fit.reference_error ** 2 - fit.model_error ** 2 >= gain_bar)


SIDE_BY_SIDE_PARALLAX_PX = 0.5
"""Least parallax (view pixels, :func:`~plenoptrack.locate.bodies.parallax_px`) of two
fitted images with a waist between them in every view for :func:`_two_images` to take
them for two particles: half the view pixel asked of images that merge. Two discs
fitted to one elongated body lie at nearly one depth (0.01-0.24 px on the `small`
camera's 0.4 mm ellipsoids of aspect up to 3, development seeds; the 1 mm ellipsoids'
halves, 0.5-0.9 px, overlap too much for a waist); two particles side by side lie at
depths of their own (0.72-0.96 px for the pairs of the 1 mm and 0.2-2 mm development
cells that only this takes apart, 0.9-1.1 mm apart in depth)."""


def _merged_in_every_view(a, b, reach) -> bool:
    """Whether images predicted at ``a`` and ``b`` (V, 2) lie closer than ``reach`` in
    every view where both are predicted."""
    d = np.hypot(*(a - b).T)
    d = d[np.isfinite(d)]
    return bool(len(d) and np.all(d < reach))


def _two_images(dlfc, params: np.ndarray, pred: np.ndarray, *,
                explained: bool = False) -> bool:
    """Whether two fitted images ``params`` (2, 5), seen at ``pred`` (2, V, 2), are two
    particles. Only parallax tells two particles from one elongated image: the images
    must move apart across the views by a view pixel and either stand apart (by the
    smaller radius) in some view or be two bodies apart in space. One convex body fitted
    with two discs puts them inside itself, overlapping in space; two large particles far
    apart in depth can overlap in every view. Where the fit ``explained`` the pixels and
    the images stand side by side in every view (a waist at least a view pixel deep
    between them, :func:`waist_depth_px`) as two bodies apart in space,
    :data:`SIDE_BY_SIDE_PARALLAX_PX` of parallax is enough."""
    offset = pred[0] - pred[1]                                                # (V, 2)
    distance = np.hypot(*offset.T)
    if not np.all(np.isfinite(distance)):
        distance = distance[np.isfinite(distance)]
    side_by_side = len(distance) > 0 and bool(
        waist_depth_px(distance, *params[:, 3]).min() >= 1.0)
    parallax = parallax_px(offset)
    if (explained and side_by_side and parallax >= SIDE_BY_SIDE_PARALLAX_PX
            and _apart_in_space(dlfc, params)):
        return True
    return bool(parallax >= 1.0
                and (np.nanmax(distance, initial=0.0) >= params[:, 3].min()
                     or _apart_in_space(dlfc, params)))


def waist_depth_px(distance, r1: float, r2: float) -> np.ndarray:
    """Depth of the waist between two overlapping discs of radii ``r1`` and ``r2`` whose
    centres lie ``distance`` apart (all view pixels): the smaller radius less the half
    length of the chord where the two circles cross (the whole smaller radius for discs
    that do not overlap, 0 for one inside the other)."""
    d = np.asarray(distance, dtype=float)
    small, large = min(r1, r2), max(r1, r2)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (d ** 2 + small ** 2 - large ** 2) / (2.0 * d)     # small centre to chord
        half_chord = np.sqrt(np.clip(small ** 2 - a ** 2, 0.0, None))
    return np.where(d >= small + large, small,
                    np.where(d + small <= large, 0.0, small - half_chord))


def _apart_in_space(dlfc, params: np.ndarray) -> bool:
    """Whether two fitted images ``params`` (2, 5: x, y, z mm, radius px, contrast) are
    two bodies that do not overlap: centres further apart than the sum of their radii,
    each radius taken to object space with the DLFC's local magnification (px per mm)."""
    radius_mm = params[:, 3] / dlfc.local_magnification(*params[:, :3].T)
    return bool(np.linalg.norm(params[0, :3] - params[1, :3]) >= radius_mm.sum())
