"""Tool posture evaluation for 3+2-axis machining (seed 001): which fixed tool orientations θ of a
ball end mill reach most of a required surface, with the cutting edge at its most efficient.

- :mod:`~stages.posture.orientations`: the orientation grid (tilts about X and Y, or polar tilt and
  azimuth) and the view frame of each orientation;
- :mod:`~stages.posture.part`: the required surface as micro-regions (triangles no longer than a size);
- :mod:`~stages.posture.offset`: the inverse offset of the ball (offset faces, arcs over sharp and
  open edges, spheres at corners), the surface the tool-tip centre can reach;
- :mod:`~stages.posture.zmap` (numpy z-buffer, the reference) and :mod:`~stages.posture.zmap_gl`
  (moderngl): the z-map along the tool axis with the generating micro-region of each cell;
- :mod:`~stages.posture.machinable`: micro-regions the tool reaches, from a z-map;
- :mod:`~stages.posture.efficiency`: the cutting efficiency λ of the edge point in contact;
- :mod:`~stages.posture.evaluate`: Φ1, Φ2 and E over the grid (eqs. 3–5);
- :mod:`~stages.posture.cover`: the greedy union of postures of section 6 (eq. 6).
"""
