"""Default actor bodies: documented dimensions, origins and radio materials per part."""

import numpy as np
import pytest

from simart_pipeline.scene import actors as bodies
from simart_pipeline.vocabulary import RADIO_MATERIALS


def test_car_dimensions_and_origin_on_the_ground():
    b = bodies.car()
    lo, hi = b.mesh.bounds
    np.testing.assert_allclose(hi[:2] - lo[:2], (4.5, 1.8), atol=1e-9)
    assert lo[2] == pytest.approx(0.2) and hi[2] == pytest.approx(1.5)  # 0.2 m clearance, no wheels


def test_quadrotor_span_is_half_a_metre_on_its_diagonal():
    b = bodies.quadrotor()
    r = np.hypot(b.mesh.vertices[:, 0], b.mesh.vertices[:, 1])
    assert r.max() == pytest.approx(0.25, abs=1e-3)
    lo, hi = b.mesh.bounds
    assert (lo[2], hi[2]) == pytest.approx((-0.03, 0.06))


def test_pedestrian_stands_on_its_origin():
    lo, hi = bodies.pedestrian().mesh.bounds
    np.testing.assert_allclose(lo, (-0.25, -0.25, 0.0), atol=1e-3)
    np.testing.assert_allclose(hi, (0.25, 0.25, 1.75), atol=1e-3)


@pytest.mark.parametrize("kind", sorted(bodies.DEFAULT_BODIES))
def test_every_face_has_a_part_with_a_radio_material(kind):
    b = bodies.DEFAULT_BODIES[kind]()
    assert b.face_part.shape == (len(b.mesh.faces),)
    assert set(b.face_part.tolist()) == set(range(len(b.part_materials)))
    assert all(m in RADIO_MATERIALS for m in b.part_materials)
