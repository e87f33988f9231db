"""A video in, an ordinary scene folder out: frames chosen by spacing and sharpness, then SfM.

    decode.py     reading frames through the `video` extra (imageio + imageio-ffmpeg), errors naming the file
    sharpness.py  a frame's sharpness (variance of the Laplacian) and the choice of frames to keep
    scene.py      video_to_scene: the stages (score, extract, SfM), reusing what an earlier call left
"""
from warpgs.data.video.decode import VIDEO_EXTENSIONS, VideoUnavailable, is_video, require_video_support
from warpgs.data.video.scene import DEFAULT_FRAMES, finished_scene, video_scene_dir, video_to_scene
from warpgs.data.video.sharpness import FrameSelection, TooFewSharpFrames, select_frames, sharpness

__all__ = ["VIDEO_EXTENSIONS", "VideoUnavailable", "is_video", "require_video_support", "DEFAULT_FRAMES",
           "finished_scene", "video_scene_dir", "video_to_scene", "FrameSelection", "TooFewSharpFrames",
           "select_frames", "sharpness"]
