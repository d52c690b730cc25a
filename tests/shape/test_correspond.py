"""Correspondence on a given surface: slid vertices go back where the model expects them."""

import numpy as np
import pytest

from pelvicnav.geometry import transforms as tf
from pelvicnav.shape.correspond import refine_correspondence
from pelvicnav.shape.mesh import edge_adjacency, vertex_normals


def _slide(vertices, faces, rng, mm):
    """Vertices moved along the surface by a smooth random tangential field, then put back on
    the surface (closest point): the same surface, another correspondence."""
    import igl

    ring, degree = edge_adjacency(faces, len(vertices))
    field = rng.normal(size=vertices.shape)
    for _ in range(30):
        field = 0.5 * field + 0.5 * (ring @ field) / degree[:, None]
    n = vertex_normals(vertices, faces)
    field -= np.einsum("ij,ij->i", field, n)[:, None] * n
    field *= mm / np.sqrt(np.mean(np.sum(field**2, axis=1)))
    _, _, c = igl.point_mesh_squared_distance(vertices + field, vertices, faces)
    return np.asarray(c)


@pytest.mark.parametrize("bone", ["sacrum", "left_hip"])
def test_slid_vertices_return_to_the_models_correspondence(bone):
    import igl

    from pelvicnav.model import load_model

    model = load_model()
    b = ("sacrum", "left_hip", "right_hip").index(bone)
    ssm, faces = model.shapes[bone], np.asarray(model.faces[b], dtype=np.int64)
    rng = np.random.default_rng(3)
    w = rng.normal(size=ssm.n_modes) * np.sqrt(ssm.variances)
    pose = tf.from_params(rng.normal(size=3) * 20, np.radians(rng.normal(size=3) * 5))
    truth = tf.apply(pose, ssm.instance(w))
    slid = _slide(truth, faces, rng, mm=4.0)
    before = np.linalg.norm(slid - truth, axis=1).mean()
    out = refine_correspondence(ssm, slid, faces)
    after = np.linalg.norm(out - truth, axis=1).mean()
    assert before > 2.5
    assert after < 0.25 * before
    # The surface is the given one: every output vertex lies on it.
    d = np.sqrt(igl.point_mesh_squared_distance(out, slid, faces)[0])
    assert d.max() < 1e-6


def test_refine_correspondence_rejects_a_mesh_of_another_topology():
    from pelvicnav.model import load_model

    model = load_model()
    ssm = model.shapes["sacrum"]
    with pytest.raises(ValueError, match="does not match"):
        refine_correspondence(ssm, ssm.mean[:-1], model.faces[0])
