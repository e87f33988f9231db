"""Camera sets for the pose-comparison tests: the same cameras in another similarity frame, a camera turned."""
import numpy as np

from warpgs.data.camera import Camera

K = np.array([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]])


def with_pose(cam: Camera, rotation: np.ndarray, centre: np.ndarray) -> Camera:
    """`cam` with its world -> camera rotation and its centre replaced."""
    V = np.array(cam.viewmat, dtype=np.float64)
    V[:3, :3] = rotation
    V[:3, 3] = -rotation @ np.asarray(centre, np.float64)
    return Camera(K, V, cam.width, cam.height, name=cam.name)


def in_other_frame(cams, Q, s=0.3, t=(4.0, 1.0, -2.0)):
    """The same cameras in another frame (SfM's gauge): world points x -> Q^T (x - t) / s, so the reference frame
    is reached by s Q x' + t."""
    return [with_pose(c, np.asarray(c.viewmat, np.float64)[:3, :3] @ Q, Q.T @ (c.center - np.asarray(t)) / s)
            for c in cams]


def turned(cam: Camera, rotation: np.ndarray) -> Camera:
    """`cam` turned in place (its centre kept): world -> camera rotation left-multiplied by `rotation`."""
    return with_pose(cam, rotation @ np.asarray(cam.viewmat, np.float64)[:3, :3], cam.center)
