"""Tool measurement (issue 6; seeds 002 and 003): the tool's contour error, runout and cutting
envelope from backlit silhouette images, the composite compensation profile, and wear.

- ``grid``: the contact-angle grid every profile is given on (0–90° in 0.1°);
- ``images``: the image files of a directory, their spindle angles, grey levels and exposure;
- ``silhouette``: one image → contour error per contact angle and side (sub-pixel edge along the
  normals of the nominal profile, robust centre fit);
- ``profile``: several images → low-pass profile (CV1 → CV2), eccentricity, envelope;
- ``composite``: seed 002's composite profile from a measured part (transitions X1, X2);
- ``wear``: wear per contact angle and rate per metre of cut (``pipeline tool-wear``);
- ``command``: ``pipeline tool-profile``, the whole job from a directory to CSV, JSON and PNG.
"""
from stages.tool_measure.command import tool_profile_command
from stages.tool_measure.composite import composite_profile, contact_angle_deg, find_transitions
from stages.tool_measure.grid import CONTACT_DEG, STEP_DEG, on_grid
from stages.tool_measure.images import IMAGE_SUFFIXES, image_levels, list_images, load_image, spindle_angles
from stages.tool_measure.profile import eccentricity, lowpass, measure_tool
from stages.tool_measure.silhouette import measure_image, measure_image_file, sample_edges, tool_radii_mm
from stages.tool_measure.wear import (cut_length_m, read_profile, run_cut_length_m, wear_profile, wear_table,
                                      write_wear)

__all__ = [
    "CONTACT_DEG", "IMAGE_SUFFIXES", "STEP_DEG", "composite_profile", "contact_angle_deg", "cut_length_m",
    "eccentricity", "find_transitions", "image_levels", "list_images", "load_image", "lowpass", "measure_image",
    "measure_image_file", "measure_tool", "on_grid", "read_profile", "run_cut_length_m", "sample_edges",
    "spindle_angles", "tool_profile_command", "tool_radii_mm", "wear_profile", "wear_table", "write_wear",
]
