"""The cutter: one axisymmetric tool family for every part of the product.

Ball, bull-nose and flat end mills are one shape: a torus corner of radius ``corner_mm`` (rc) on a
core disk of radius R − rc, closed above by the shank cylinder of radius R up to ``stickout_mm``.
Ball: rc = R; flat: rc = 0. Everything that needs the tool (rendering, forces, errors, correction,
gap diagnosis, the virtual machine) takes a :class:`Cutter` built once by :meth:`Cutter.from_params`
from the workflow's ``tool`` entry; derived radii are never recomputed elsewhere.

Frame: tip at the origin, axis +Z. Contact angle q: 0° at the tip, 90° on the side (DESIGN §5);
rotation angle φ counter-clockwise from the feed direction, seen from above.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages import InputError

KINDS = ("ball", "bull", "flat")
DEFAULT_STICKOUT_MM = 40.0
DEFAULT_FLUTES = 2
DEFAULT_HELIX_DEG = 30.0


@dataclass(frozen=True)
class Cutter:
    """Axisymmetric end mill. Lengths in mm, angles in degrees.

    Attributes
    ----------
    kind : "ball" | "bull" | "flat"
    radius_mm : R = diameter / 2
    corner_mm : rc (R for a ball, 0 for a flat end mill)
    stickout_mm : length from the tip to the holder (closes the envelope above)
    flutes, helix_deg, runout_um : the cutting edges (runout: axis eccentricity towards flute 0)
    control_point : "tip" (NC coordinates are the tool tip) or "center" (the corner's centre)
    profile : path of the measured contour-error table (claim 2), or None
    """

    kind: str
    radius_mm: float
    corner_mm: float
    stickout_mm: float = DEFAULT_STICKOUT_MM
    flutes: int = DEFAULT_FLUTES
    helix_deg: float = DEFAULT_HELIX_DEG
    runout_um: float = 0.0
    control_point: str = "tip"
    profile: str | None = None

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_params(cls, tool) -> "Cutter":
        """The cutter of a workflow ``tool`` entry (a dict as the config dumps it).

        A list of tools must have been resolved to the program's entry; a list of one is accepted.
        Raises :class:`stages.InputError` naming the key for a missing or inconsistent value.
        """
        if isinstance(tool, Cutter):
            return tool
        if isinstance(tool, (list, tuple)):
            if len(tool) != 1:
                raise InputError("tool: one tool per program expected, got a list of "
                                 f"{len(tool)} (select the entry for the program's T number)")
            tool = tool[0]
        try:
            kind = tool["type"]
            radius = float(tool["diameter_mm"]) / 2.0
        except (KeyError, TypeError) as e:
            raise InputError(f"tool: missing key {e}") from None
        if kind not in KINDS:
            raise InputError(f"tool.type: unknown tool type {kind!r} (ball, bull, flat)")
        if not radius > 0:
            raise InputError(f"tool.diameter_mm: must be > 0, got {2 * radius}")
        rc = tool.get("corner_radius_mm")
        if kind == "ball":
            rc = radius
        elif kind == "flat":
            rc = 0.0
        elif rc is None or not (0 < float(rc) < radius):
            raise InputError(f"tool.corner_radius_mm: a bull-nose tool needs 0 < rc < {radius}, got {rc}")
        stickout = float(tool.get("stickout_mm") or DEFAULT_STICKOUT_MM)
        control = tool.get("control_point") or "tip"
        if control == "center" and kind == "flat":
            raise InputError("tool.control_point: center needs a corner radius (ball or bull-nose)")
        return cls(kind=kind, radius_mm=radius, corner_mm=float(rc),
                   stickout_mm=max(stickout, radius + 1e-3),
                   flutes=int(tool.get("flutes") or DEFAULT_FLUTES),
                   helix_deg=float(DEFAULT_HELIX_DEG if tool.get("helix_deg") is None else tool["helix_deg"]),
                   runout_um=float(tool.get("runout_um") or 0.0), control_point=control,
                   profile=tool.get("profile"))

    # ------------------------------------------------------------------ derived quantities
    @property
    def diameter_mm(self) -> float:
        return 2.0 * self.radius_mm

    @property
    def core_mm(self) -> float:
        """Radius of the flat core disk, R − rc."""
        return self.radius_mm - self.corner_mm

    @property
    def control_offset_mm(self) -> float:
        """Height of the NC control point above the tip (0 for tip programs, rc for centre programs)."""
        return self.corner_mm if self.control_point == "center" else 0.0

    # ------------------------------------------------------------------ the envelope
    def profile_radius(self, z_mm):
        """Radius of the envelope at height ``z_mm`` above the tip (NaN below the tip)."""
        z = np.asarray(z_mm, dtype=float)
        R, rc = self.radius_mm, self.corner_mm
        with np.errstate(invalid="ignore"):
            corner = (R - rc) + np.sqrt(np.clip(rc * rc - (rc - z) ** 2, 0.0, None))
        r = np.where(z >= rc, R, corner)
        return np.where(z < 0, np.nan, r)

    def lowest_z(self, r_mm):
        """Height above the tip of the lowest envelope point at radius ``r_mm`` (NaN beyond R)."""
        R, rc = self.radius_mm, self.corner_mm
        r = np.asarray(r_mm, float)
        with np.errstate(invalid="ignore"):
            corner = rc - np.sqrt(np.clip(rc * rc - (r - (R - rc)) ** 2, 0.0, None))
        z = np.where(r <= R - rc, 0.0, corner)
        return np.where(r <= R, z, np.nan)

    def immersion(self, z_mm):
        """Envelope radius r(z) and axial immersion angle κ(z) (rad) at heights ``z_mm``.

        On the corner (z < rc): z = rc(1 − cos κ), r = R − rc + rc sin κ; above it κ = 90°, r = R.
        """
        z = np.asarray(z_mm, dtype=float)
        if self.corner_mm <= 0:
            return np.full_like(z, self.radius_mm), np.full_like(z, np.pi / 2)
        zc = np.clip(z, 0.0, self.corner_mm)
        kappa = np.arccos(1.0 - zc / self.corner_mm)
        return self.radius_mm - self.corner_mm + self.corner_mm * np.sin(kappa), kappa

    def generator_length(self, z_mm):
        """Arc length of the envelope's generator from the corner's start up to height z."""
        z = np.asarray(z_mm, dtype=float)
        rc = self.corner_mm
        if rc <= 0:
            return np.maximum(z, 0.0)
        zc = np.clip(z, 0.0, rc)
        return rc * np.arccos(1.0 - zc / rc) + np.maximum(z - rc, 0.0)

    def corner_height(self, contact_deg):
        """Height above the tip of the corner point at contact angle q (clipped to 0–90°)."""
        q = np.radians(np.clip(np.asarray(contact_deg, dtype=float), 0.0, 90.0))
        return self.corner_mm * (1.0 - np.cos(q))

    def helix_lag_deg(self, z_mm):
        """Angular lag of the edge at height z behind its tip end: z·tan β / R (constant lead)."""
        return np.degrees(np.asarray(z_mm, dtype=float) * np.tan(np.radians(self.helix_deg)) / self.radius_mm)

    def flute_offsets_mm(self, runout_um: float | None = None) -> np.ndarray:
        """Radial offset of each flute for an axis eccentricity (default the cutter's runout) towards flute 0."""
        e = self.runout_um if runout_um is None else runout_um
        j = np.arange(self.flutes)
        return (float(e) * 1e-3) * np.cos(2 * np.pi * j / self.flutes)

    def point(self, q_deg, phi_deg, feed_deg=0.0):
        """Envelope point (tip frame) at contact angle ``q`` and rotation angle ``phi`` from the
        feed direction ``feed_deg``. Returns (..., 3)."""
        q = np.radians(np.asarray(q_deg, dtype=float))
        th = np.radians(np.asarray(phi_deg, dtype=float) + feed_deg)
        R, rc = self.radius_mm, self.corner_mm
        r = (R - rc) + rc * np.sin(q)
        z = rc * (1.0 - np.cos(q))
        return np.stack(np.broadcast_arrays(r * np.cos(th), r * np.sin(th), z), axis=-1)

    def distance(self, rel):
        """Signed distance from points to the tool (tip at the origin, axis +z), and where it is.

        Parameters
        ----------
        rel : ndarray (..., 3), points relative to the tip, mm

        Returns
        -------
        dist : (...) mm to the tool surface, negative inside (the depth there); above the
            stick-out nothing of the tool cuts
        contact_deg : (...) contact angle q of the nearest tool point (0 at the tip, 90 on the side)
        height_mm : (...) height of the nearest tool point above the tip
        normal : (..., 3) outward unit normal of the tool there
        """
        R, rc = self.radius_mm, self.corner_mm
        a = R - rc                                           # radius of the circle of corner centres
        x, y, h = rel[..., 0], rel[..., 1], rel[..., 2]
        r = np.hypot(x, y)
        with np.errstate(invalid="ignore", divide="ignore"):
            ux = np.where(r > 1e-12, x / np.where(r > 1e-12, r, 1.0), 1.0)
            uy = np.where(r > 1e-12, y / np.where(r > 1e-12, r, 1.0), 0.0)
        dr, dh = r - a, h - rc
        on_bottom = r <= a                                   # under (or inside) the flat bottom
        on_side = ~on_bottom & (dh > 0)                      # beside the cylindrical side
        rho = np.hypot(np.maximum(dr, 0.0), np.minimum(dh, 0.0))
        q_corner = np.degrees(np.arctan2(np.maximum(dr, 0.0), -np.minimum(dh, 0.0)))
        dist = np.where(on_bottom, -h, np.where(on_side, r - R, rho - rc))
        dist = np.where(h > self.stickout_mm, np.maximum(dist, h - self.stickout_mm), dist)
        q = np.where(on_bottom, 0.0, np.where(on_side, 90.0, q_corner))
        height = np.where(on_bottom, 0.0, np.where(on_side, np.clip(h, rc, self.stickout_mm),
                                                   rc * (1.0 - np.cos(np.radians(q)))))
        qr = np.radians(q)
        normal = np.stack([np.sin(qr) * ux, np.sin(qr) * uy, -np.cos(qr)], axis=-1)
        return dist, q, height, normal

    def clearance(self, points):
        """Distance of ``points`` (tip frame, (..., 3) mm) from the tool body, and its direction.

        The body is the corner torus about the core disk (a ball for rc = R, the flat end's rim for
        rc = 0) closed above by the shank cylinder of radius R. Negative inside.

        Returns
        -------
        (d, u): (...,) mm and (..., 3) unit vectors from the nearest body point towards the point
        (a move of the tool reduces the clearance by u·move); u is NaN on the axis inside the body.
        """
        p = np.asarray(points, dtype=float)
        R, rc = self.radius_mm, self.corner_mm
        rho = np.hypot(p[..., 0], p[..., 1])
        radial = np.stack([p[..., 0], p[..., 1]], -1) / np.where(rho > 1e-12, rho, np.inf)[..., None]
        above = p[..., 2] >= rc
        vr = np.where(above, rho - R, rho - np.minimum(rho, R - rc))
        vz = np.where(above, 0.0, p[..., 2] - rc)
        length = np.hypot(vr, vz)
        d = np.where(above, rho - R, length - rc)
        sign = np.where(above, 1.0, 1.0 / np.where(length > 1e-12, length, np.nan))
        ur, uz = np.where(above, 1.0, vr * sign), np.where(above, 0.0, vz * sign)
        u = np.concatenate([radial * ur[..., None], uz[..., None]], -1)
        u[(rho <= 1e-12) & above] = np.nan
        return d, u
