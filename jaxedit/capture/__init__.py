"""From photos or a video to a posed nerfstudio dataset: structure from motion with COLMAP.

    from jaxedit import capture
    images = capture.list_images("photos/")
    capture.check_images(images, "photos/")                # >= 3 readable images of one size
    summary = capture.process_capture("data/", images)     # SIFT, matching, mapping, dataset
    frames, index, scores = capture.sample_video("clip.mp4", 150)   # sharpest frame per window
    pts, rgb = capture.points.random_points(images, cameras, 20000, key)  # when a dataset has no cloud

:mod:`.sfm` needs the optional extra ``capture`` (pycolmap; imageio-ffmpeg for
videos); the rest (alignment, frame scores) needs only the core dependencies.
"""

from . import points
from .align import camera_extent, pose_errors, umeyama
from .dataset import (APPLIED_TRANSFORM, CaptureConfig, colmap_intrinsics, process_capture,
                      reconstruction_points, reconstruction_views, transforms_meta)
from .frames import blur_score, check_images, list_images, sample_video, windows
from .sfm import SfmOptions, image_pairs, quiet_colmap, run_sfm

__all__ = ["APPLIED_TRANSFORM", "points", "SfmOptions", "blur_score", "camera_extent", "check_images",
           "CaptureConfig", "colmap_intrinsics", "image_pairs", "list_images", "pose_errors", "process_capture",
           "quiet_colmap", "reconstruction_points", "reconstruction_views", "run_sfm",
           "sample_video", "transforms_meta", "umeyama", "windows"]
