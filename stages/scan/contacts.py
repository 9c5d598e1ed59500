"""Contacts of a pass read from the pixels of M: angles, normal, the design surface, second contacts.
"""
from __future__ import annotations

import numpy as np


# with the design model given (workflow ``nominal``), surviving pixels farther than this from it are
# rest material the program leaves for another (a pass down a wall into a pocket corner rides over
# the stock the semi-finishing left there, 0.5-1.7 mm off the model on the sample), not the design
# surface the pass finishes; the generating point is taken on the design surface where the pass
# leaves any. Over cusps, CAM and render tolerance and the moves of a correction round (a corrected
# path's envelope lies up to correct.max_move_um off the model by construction; 0.3 mm on the
# sample), under the rest material.
DESIGN_TOL_MM = 0.35


# the pixels deepest into the design surface, within this of the deepest: the pass's contact (a ball
# lifts 10 µm off a plane 0.32 mm from its contact point; the sample's cusps are 9 µm high, so
# between two rows the band is the whole strip the pass leaves, as without the model)
CONTACT_BAND_MM = 0.01


# the strip estimate of a pass lost from below (strip_estimate) with the design model: the strip
# points within this of the deepest into the model aim the view (wide enough to hold the contact's
# neighbourhood on a wall the tool climbs: the side departs from a 2° draft by 0.1 mm over 3 mm),
# from at most this many strip points
STRIP_BAND_MM = 0.1


STRIP_DESIGN_POINTS = 4000


# a second contact (second_estimate): strip points more than SECOND_DEG off the generating point's
# normal, the deepest of them within SECOND_TOL_MM of the generating point's depth into the model
# (the rest material across a pocket corner the pass does not reach lies 0.5 mm and more off it;
# the sample's y wall at x 73.5, y 53, which the row y 48 does cut, 0.09-0.25 mm), the patch of those within
# CONTACT_BAND_MM of that deepest within SECOND_SPREAD_DEG of its mean direction (a ball in a
# plane's contact: ±5° for the band; a fillet of the ball's own radius: the whole arc, rejected)
SECOND_DEG = 30.0


SECOND_TOL_MM = DESIGN_TOL_MM


SECOND_SPREAD_DEG = 15.0


def on_design(design, view, M, mask, tol_mm=DESIGN_TOL_MM):
    """The pixels of ``mask`` where the pass touches the design surface: the deepest into it
    (signed distance, within :data:`CONTACT_BAND_MM` of the lowest), when the lowest lies within
    ``tol_mm`` above it; all of ``mask`` when the design model is not given or none is that low.

    Deepest, not nearest: a path a correction round moved into the material leaves its envelope
    under the model, and its pixels nearest the model are where it meets the neighbouring row's
    surface, off its contact."""
    if design is None or not mask.any():
        return mask
    rows, cols = np.nonzero(mask)
    pts = view.pixel_points(rows, cols, M.depth[mask])
    dist = design.signed_distance(pts)
    if not dist.min() <= tol_mm:
        return mask
    near = dist <= dist.min() + CONTACT_BAND_MM
    out = np.zeros_like(mask)
    out[rows[near], cols[near]] = True
    return out


def angles(M, mask):
    """Mean contact and rotation angle of the pixels ``mask`` of layer M, read from the pixels.

    The (q, φ) of each pixel is a direction on the unit sphere (the envelope normal); their mean
    direction gives the mean angles. Unlike averaging q and φ separately this has no bias near
    the tip (q = 0, where φ is undefined and q is never negative) and no wrap at φ = 0/360°.
    """
    q = np.radians(M.b[mask].astype(float))
    a = np.radians(M.a[mask].astype(float))
    v = np.array([np.mean(np.sin(q) * np.cos(a)), np.mean(np.sin(q) * np.sin(a)),
                  np.mean(np.cos(q))])
    qm = float(np.degrees(np.arctan2(np.hypot(v[0], v[1]), v[2])))
    phi = float(np.degrees(np.arctan2(v[1], v[0])) % 360.0)
    return qm, phi


def material_normal(q_deg, phi_deg, feed_deg):
    """Surface normal out of the material at the contact point (q, φ) of the envelope."""
    q, th = np.radians(q_deg), np.radians(phi_deg + feed_deg)
    return np.array([-np.sin(q) * np.cos(th), -np.sin(q) * np.sin(th), np.cos(q)])


def strip_points(shape, E, dz, n_phi, u, feed_deg, width=0.1):
    """The engaged envelope points of the own-path strip (|N·u| < ``width``, N the envelope normal)
    of engagement grid ``E``: their grid indices (k, j), contact angles q and world azimuths θ (rad)
    and envelope normals N (world frame, out of the tool: minus the material's normal there)."""
    n_z = E.shape[0]
    z = (np.arange(n_z) + 0.5) * dz
    rc = max(shape.corner_mm, 1e-9)
    q = np.where(z < rc, np.arccos(np.clip((rc - z) / rc, -1.0, 1.0)), np.pi / 2)
    th = np.radians((np.arange(n_phi) + 0.5) * 360.0 / n_phi + feed_deg)
    u = np.asarray(u, float)
    # N·u = sin q (cos θ u_x + sin θ u_y) − cos q u_z, an outer product: the grid's normals are
    # formed only at the strip's points (a wall climb's grid holds 10⁵–10⁶ points)
    nu = np.sin(q)[:, None] * (np.cos(th) * u[0] + np.sin(th) * u[1])[None] - (np.cos(q) * u[2])[:, None]
    kk, jj = np.nonzero(E & (np.abs(nu) < width))
    qs, ts = q[kk], th[jj]
    return kk, jj, qs, ts, np.stack([np.sin(qs) * np.cos(ts), np.sin(qs) * np.sin(ts), -np.cos(qs)], axis=1)


def strip_world(shape, tip, dz, kk, th):
    """World coordinates of strip points at levels ``kk`` and azimuths ``th`` of the tool at ``tip``."""
    z = (kk + 0.5) * dz
    r = shape.profile_radius(z)
    return np.asarray(tip, float)[:3] + np.stack([r * np.cos(th), r * np.sin(th), z], axis=1)


def mean_angles(q, th, feed_deg):
    """(q, φ) in degrees, φ from the feed direction, of the mean of envelope directions (q, θ)."""
    v = np.array([np.mean(np.sin(q) * np.cos(th)), np.mean(np.sin(q) * np.sin(th)), np.mean(np.cos(q))])
    return (float(np.degrees(np.arctan2(np.hypot(v[0], v[1]), v[2]))),
            float((np.degrees(np.arctan2(v[1], v[0])) - feed_deg) % 360.0))


def strip_estimate(shape, E, dz, n_phi, u, feed_deg, width=0.1, tip=None, design=None):
    """(q, φ) of the mean direction of the engaged envelope points with |N·u| < ``width``.

    ``E`` is the engagement grid (axial levels × rotation angles, see :func:`unpack_engagement`);
    N is the envelope normal at a grid point. With the design model and the ``tip`` (world
    coordinates of the grid's origin), only the strip points deepest into the design surface
    count (within :data:`STRIP_BAND_MM`, when the deepest lies within :data:`DESIGN_TOL_MM`): in
    a pocket corner the strip also runs through the rest material on the wall across, and the
    mean of all of it points between the walls (sample: the passes climbing the pocket's x wall
    0.9 mm from the y wall's rest material, φ 32–41° against the contact's 4°; the view aimed
    there saw nothing, or a few pixels of its edge, and the pass had no generating point or a
    wrong one). Returns None when no such point is engaged.
    """
    kk, jj, q, th, _ = strip_points(shape, E, dz, n_phi, u, feed_deg, width)
    if not len(kk):
        return None
    if design is not None and tip is not None:
        take = np.linspace(0, len(kk) - 1, min(len(kk), STRIP_DESIGN_POINTS)).astype(np.int64)
        kk, q, th = kk[take], q[take], th[take]
        sd = design.signed_distance(strip_world(shape, tip, dz, kk, th))
        if sd.min() <= DESIGN_TOL_MM:
            # the patch around the deepest point: in a vertical corner both walls lie within the
            # band, and their mean aims between them at neither (the second contact is found later)
            i = int(np.argmin(sd))
            near = (np.sin(q) * np.sin(q[i]) * np.cos(th - th[i]) + np.cos(q) * np.cos(q[i])
                    > np.cos(np.radians(SECOND_DEG)))
            deep = (sd <= sd.min() + STRIP_BAND_MM) & near
            q, th = q[deep], th[deep]
    return mean_angles(q, th, feed_deg)


def second_estimate(shape, E, dz, n_phi, u, feed_deg, tip, design, n1, c1, width=0.1):
    """(q, φ) where the pass touches the design surface a second time, or None.

    A ball in a pocket's vertical corner finishes both walls at once, and one on a floor beside a
    wall its foot too: two contacts whose normals lie far apart, with no contact between them.
    One generating point stands for one of them (from below a vertical wall is edge-on; along one
    wall's normal the other is), and on the sample's corner climbs (source lines 3996 and 3999)
    which one changed from piece to piece with the pixels each piece happened to cut. The second
    contact is sought on the engaged strip (as :func:`strip_estimate`): its points more than
    :data:`SECOND_DEG` off the generating point's normal ``n1`` whose deepest lies within
    :data:`SECOND_TOL_MM` of the generating point ``c1``'s depth into the model (so not the rest
    material across a corner, 0.5–1.7 mm off it), separated from the first (no strip point between
    half that angle and it within 2 × :data:`CONTACT_BAND_MM` of that depth: a ball rolling in a
    fillet of its own radius touches along the whole arc, which is one contact), and whose points
    within :data:`CONTACT_BAND_MM` of that deepest form one tight patch (within
    :data:`SECOND_SPREAD_DEG` of their mean).
    """
    kk, jj, q, th, N = strip_points(shape, E, dz, n_phi, u, feed_deg, width)
    cos_a = -(N @ np.asarray(n1, float))                  # cosine of each point's angle off n1
    if not (cos_a < np.cos(np.radians(SECOND_DEG))).any():
        return None
    take = np.linspace(0, len(kk) - 1, min(len(kk), STRIP_DESIGN_POINTS)).astype(np.int64)
    kk, q, th, cos_a = kk[take], q[take], th[take], cos_a[take]
    far = cos_a < np.cos(np.radians(SECOND_DEG))
    if not far.any():
        return None
    sd = design.signed_distance(strip_world(shape, tip, dz, kk, th))
    sd1 = float(design.signed_distance(np.asarray(c1, float)[None])[0])
    sd2 = float(sd[far].min())
    if not sd2 <= sd1 + SECOND_TOL_MM:
        return None
    # a contact that runs on from the first to the second (a fillet) is one contact: none of the
    # strip between SECOND_DEG / 2 and SECOND_DEG off n1 lies that close to the model
    between = (cos_a < np.cos(np.radians(SECOND_DEG / 2))) & ~far
    if (between & (sd <= sd2 + 2 * CONTACT_BAND_MM)).any():
        return None
    deep = far & (sd <= sd2 + CONTACT_BAND_MM)
    q, th = q[deep], th[deep]
    q2, phi2 = mean_angles(q, th, feed_deg)
    m2 = material_normal(q2, phi2, feed_deg)
    own = np.stack([-np.sin(q) * np.cos(th), -np.sin(q) * np.sin(th), np.cos(q)], axis=1)
    if np.min(own @ m2) < np.cos(np.radians(SECOND_SPREAD_DEG)):
        return None
    return q2, phi2


def store(gen, slot, view, M, mask, q, phi, feed, how, all_mask=None):
    """Generating point of ``slot`` from the pixels ``mask``; the direction the engagement is read
    along (:func:`engagement_along_normal`) from ``all_mask`` (default ``mask``): every pixel the
    pass leaves, rest material included, as before the design surface was told apart."""
    rows, cols = np.nonzero(mask)
    pts = view.pixel_points(rows, cols, M.depth[mask])
    c = pts.mean(0)
    nrm = material_normal(q, phi, feed)
    if all_mask is not None and not np.array_equal(all_mask, mask):
        ra, ca = np.nonzero(all_mask)
        qa, pa_ = angles(M, all_mask)
        gen["eng_c"][slot] = view.pixel_points(ra, ca, M.depth[all_mask]).mean(0)
        gen["eng_n"][slot] = material_normal(qa, pa_, feed)
    else:
        gen["eng_c"][slot], gen["eng_n"][slot] = c, nrm
    gen["gen_x_mm"][slot], gen["gen_y_mm"][slot], gen["gen_z_mm"][slot] = c
    gen["rotation_deg"][slot] = phi
    gen["contact_deg"][slot] = q
    gen["nx"][slot], gen["ny"][slot], gen["nz"][slot] = nrm
    gen["n_px"][slot] = int(mask.sum())
    gen["view"][slot] = how


SECOND_COLUMNS = ("gen2_x_mm", "gen2_y_mm", "gen2_z_mm", "rotation2_deg", "contact2_deg", "nx2", "ny2", "nz2")


def store_second(gen, slot, view, M, mask, q, phi, feed):
    """Second contact of ``slot`` from the pixels ``mask`` (the ``*2`` columns)."""
    rows, cols = np.nonzero(mask)
    c = view.pixel_points(rows, cols, M.depth[mask]).mean(0)
    values = (*c, phi, q, *material_normal(q, phi, feed))
    for key, v in zip(SECOND_COLUMNS, values):
        gen[key][slot] = v
    gen["n2_px"][slot] = int(mask.sum())
