"""lab.data.scenes: the ray caster (exact depth, mask, anti-aliasing, lens distortion), objects and textures."""

import cv2
import numpy as np
import pytest
import trimesh

from lab.core import Cameras, Image, InvalidValue
from lab.data.scenes import (Box, MeshObject, Plane, Rendering, Scene, Sphere, Texture, moller_trumbore, pixel_rays,
                             render, render_views)
from lab.data.scenes.objects import _embree_available, binned_moller_trumbore
from lab.geometry.rotations import look_at, matrix_to_rotvec, rotvec_to_matrix

W, H = 96, 72
K = np.array([[80.0, 0.0, 47.5], [0.0, 78.0, 35.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.25, 0.07, 0.001, -0.0008, 0.0])
WHITE = (1.0, 1.0, 1.0)


def camera(R=np.eye(3), t=np.zeros(3), K=K, dist=None, width=W, height=H) -> Cameras:
    return Cameras(K, R, t, width, height, dist=dist)


def unlit(*objects, background=(0.0, 0.0, 0.0)) -> Scene:
    return Scene(tuple(objects), background=background, light=None)


def rays_of(K_: np.ndarray, width: int, height: int) -> np.ndarray:
    """Camera-frame rays (x, y, 1) of every pixel centre of an undistorted camera, by K^-1: (H, W, 3)."""
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K_).T
    return rays / rays[..., 2:3]


def opencv_pixels(X: np.ndarray, cams: Cameras, index: int = 0) -> np.ndarray:
    dist = np.zeros(5) if cams.dist is None else cams.dist[index]
    pixels, _ = cv2.projectPoints(X.reshape(-1, 1, 3), matrix_to_rotvec(cams.R[index]), cams.t[index],
                                  cams.K[index], dist)
    return pixels.reshape(-1, 2)


# --- smoke and shapes -----------------------------------------------------------------------------------------
def test_render_returns_image_depth_mask_and_ids():
    scene = unlit(Sphere((0.0, 0.0, 3.0), 0.5, color=(0.2, 0.4, 0.6)), background=(0.5, 0.5, 0.5))
    view = render(scene, camera(), 0)
    assert isinstance(view, Rendering) and isinstance(view.image, Image)
    assert view.image.pixels.shape == (H, W, 3) and view.image.pixels.dtype == np.float32
    assert view.depth.shape == (H, W) and view.depth.dtype == np.float64
    assert view.mask.shape == (H, W) and view.mask.dtype == np.bool_
    assert view.object_ids.shape == (H, W)
    assert 0.0 <= view.image.pixels.min() and view.image.pixels.max() <= 1.0
    np.testing.assert_array_equal(view.mask, np.isfinite(view.depth))
    np.testing.assert_array_equal(view.object_ids, np.where(view.mask, 0, -1))
    np.testing.assert_allclose(view.image.pixels[0, 0], 0.5)  # the background
    np.testing.assert_allclose(view.image.pixels[H // 2, W // 2], (0.2, 0.4, 0.6), atol=1e-6)


def test_render_views_renders_every_camera_in_order():
    scene = unlit(Plane.centered((0.0, 0.0, 0.0), (1, 0, 0), (0, 1, 0), (4.0, 4.0), color=WHITE))
    R, t = look_at(np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]]), np.zeros((2, 3)), (0.0, 1.0, 0.0))
    views = render_views(scene, Cameras(np.stack([K, K]), R, t, W, H), supersample=1)
    assert len(views) == 2
    np.testing.assert_allclose(views[0].depth[H // 2, W // 2], 2.0, rtol=1e-12)
    np.testing.assert_allclose(views[1].depth[H // 2, W // 2], 3.0, rtol=1e-12)


# --- exact depth ------------------------------------------------------------------------------------------------
def test_depth_of_a_tilted_plane_is_exact_at_every_pixel():
    R = rotvec_to_matrix(np.array([0.15, -0.2, 0.05]))
    t = np.array([0.1, -0.2, 2.5])
    plane = Plane.centered((0.0, 0.0, 0.0), (1, 0, 0), (0, 1, 0), (30.0, 30.0), color=WHITE)
    view = render(unlit(plane), camera(R, t), supersample=2)
    # closed form: the world plane z = 0 is n_c . X_c = d_c in the camera frame; Z = d_c / (n_c . (x, y, 1))
    n_c = R @ np.array([0.0, 0.0, 1.0])
    d_c = n_c @ t
    expected = d_c / (rays_of(K, W, H) @ n_c)
    assert view.mask.all()
    np.testing.assert_allclose(view.depth, expected, rtol=1e-12)


def test_depth_of_a_sphere_matches_the_closed_form():
    centre, radius = np.array([0.3, -0.2, 4.0]), 1.1
    view = render(unlit(Sphere(centre, radius, color=WHITE)), camera(), supersample=1)
    rays = rays_of(K, W, H).reshape(-1, 3)
    a = np.einsum("ij,ij->i", rays, rays)
    b = rays @ centre
    disc = b * b - a * (centre @ centre - radius ** 2)
    expected = np.where(disc >= 0, (b - np.sqrt(np.maximum(disc, 0))) / a, np.inf).reshape(H, W)
    clear = np.abs(disc.reshape(H, W)) > 1e-9  # pixels not grazing the silhouette
    np.testing.assert_array_equal(view.mask[clear], np.isfinite(expected)[clear])
    inside = np.isfinite(expected) & clear
    assert inside.sum() > 0.15 * W * H
    np.testing.assert_allclose(view.depth[inside], expected[inside], rtol=1e-12)


def test_box_depth_and_faces_from_inside_and_outside():
    box = Box((0.0, 0.0, 5.0), (2.0, 2.0, 2.0), color=WHITE)
    view = render(unlit(box), camera(), supersample=1)
    np.testing.assert_allclose(view.depth[H // 2, W // 2], 4.0, rtol=1e-12)  # the face z = 4 facing the camera
    inside = render(unlit(box), camera(t=np.array([0.0, 0.0, -5.0])), supersample=1)  # camera at the box centre
    assert inside.mask.all()
    np.testing.assert_allclose(inside.depth[H // 2, W // 2], 1.0, rtol=1e-12)  # the far face, z = 6 in the world


def test_depth_comes_from_the_pixel_centre_not_an_average_across_an_edge():
    near = Plane((-5.0, -5.0, 2.0), (1, 0, 0), (0, 1, 0), (5.0 + 0.0123, 10.0), color=WHITE)  # left part, Z = 2
    far = Plane.centered((0.0, 0.0, 3.0), (1, 0, 0), (0, 1, 0), (10.0, 10.0), color=(0.0, 0.0, 0.0))
    view = render(unlit(near, far), camera(), supersample=4)
    assert set(np.unique(view.depth)) == {2.0, 3.0}
    edge_column = K[0, 2] + K[0, 0] * 0.0123 / 2.0
    columns = np.arange(W)
    np.testing.assert_array_equal(view.depth[10], np.where(columns <= edge_column, 2.0, 3.0))
    partly = int(np.floor(edge_column + 0.5))  # the pixel the edge crosses: a grey mix in the image
    assert 0.0 < view.image.pixels[10, partly, 0] < 1.0


def test_nearest_object_wins_and_ids_name_it():
    front = Sphere((0.0, 0.0, 3.0), 0.4, color=(1.0, 0.0, 0.0))
    back = Plane.centered((0.0, 0.0, 6.0), (1, 0, 0), (0, 1, 0), (20.0, 20.0), color=(0.0, 1.0, 0.0))
    for objects, sphere_id in (((front, back), 0), ((back, front), 1)):
        view = render(unlit(*objects), camera(), supersample=1)
        assert view.object_ids[H // 2, W // 2] == sphere_id
        np.testing.assert_allclose(view.image.pixels[H // 2, W // 2], (1.0, 0.0, 0.0))
        np.testing.assert_allclose(view.depth[0, 0], 6.0 * np.linalg.norm([1.0]), rtol=1e-12)


# --- projection consistency -------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["plane", "sphere", "box", "mesh"])
def test_a_point_on_a_surface_projects_to_a_pixel_whose_depth_is_its_z(kind):
    """cv2.projectPoints puts a surface point at (u, v); shifting the principal point by the fraction makes
    (u, v) a pixel centre; the depth rendered there must be the point's Z (with lens distortion)."""
    rng = np.random.default_rng({"plane": 1, "sphere": 2, "box": 3, "mesh": 4}[kind])
    R = rotvec_to_matrix(np.array([0.1, 0.25, -0.05]))
    t = np.array([-0.1, 0.05, 3.0])
    centre = -R.T @ t
    if kind == "plane":
        obj = Plane.centered((0.0, 0.0, 0.0), (1, 0, 0), (0, 1, 0), (3.0, 3.0), color=WHITE)
        points = np.c_[rng.uniform(-0.5, 0.5, (6, 2)), np.zeros(6)]
    elif kind == "sphere":
        obj = Sphere((0.0, 0.0, 0.0), 0.6, color=WHITE)
        towards = (centre / np.linalg.norm(centre) + rng.normal(0, 0.25, (6, 3)))
        points = 0.6 * towards / np.linalg.norm(towards, axis=1, keepdims=True)
    elif kind == "box":
        obj = Box((0.0, 0.0, 0.0), (1.0, 0.8, 0.6), rotation=rotvec_to_matrix(np.array([0.0, 0.0, 0.3])),
                  color=WHITE)
        axis = int(np.argmax(np.abs(obj.rotation.T @ centre) / (0.5 * np.array(obj.size))))
        sign = np.sign((obj.rotation.T @ centre)[axis])
        local = rng.uniform(-0.4, 0.4, (6, 3)) * np.array(obj.size)
        local[:, axis] = sign * 0.5 * obj.size[axis]
        points = local @ obj.rotation.T
    else:
        obj = MeshObject(trimesh.creation.icosphere(subdivisions=2, radius=0.6), color=WHITE)
        mesh = obj.mesh
        front = np.flatnonzero(mesh.face_normals @ centre > 0.5)
        faces = rng.choice(front, 6, replace=False)
        w = rng.dirichlet(np.ones(3), 6)
        points = np.einsum("nk,nkj->nj", w, mesh.vertices[mesh.faces[faces]])
    for X in points:
        uv = opencv_pixels(X, camera(R, t, dist=DIST))[0]
        target = np.round(uv)
        K_shift = K.copy()
        K_shift[:2, 2] += target - uv
        cams = camera(R, t, K=K_shift, dist=DIST)
        np.testing.assert_allclose(opencv_pixels(X, cams)[0], target, atol=1e-9)
        view = render(unlit(obj), cams, supersample=1)
        u, v = target.astype(int)
        np.testing.assert_allclose(view.depth[v, u], (R @ X + t)[2], rtol=1e-9)
        assert view.object_ids[v, u] == 0


def test_back_projected_depth_reprojects_onto_its_pixel_with_opencv():
    R = rotvec_to_matrix(np.array([-0.1, 0.3, 0.2]))
    t = np.array([0.2, 0.1, 2.0])
    cams = camera(R, t, dist=DIST)
    scene = unlit(Sphere((0.0, 0.0, 0.0), 0.7, color=WHITE),
                  Box((0.9, 0.0, 0.0), (0.5, 0.5, 0.5), color=WHITE),
                  Plane.centered((0.0, 0.0, -0.8), (1, 0, 0), (0, 1, 0), (6.0, 6.0), color=WHITE))
    view = render(scene, cams, supersample=1)
    origin, directions = pixel_rays(cams, 0)
    np.testing.assert_allclose(origin, cams.centers[0])
    v, u = np.nonzero(view.mask)
    X = origin + view.depth[v, u, None] * directions[v, u]
    np.testing.assert_allclose(opencv_pixels(X, cams), np.c_[u, v], atol=1e-6)
    np.testing.assert_allclose((X @ R.T + t)[:, 2], view.depth[v, u], rtol=1e-12)


# --- distortion ---------------------------------------------------------------------------------------------------
def test_a_straight_3d_edge_renders_curved_exactly_as_cv2_project_points_predicts():
    """A white half-plane x >= 0.8 on black: the rendered edge must follow the projection of the 3D line."""
    dist = np.array([-0.35, 0.12, 0.0, 0.0, 0.0])
    edge_x = 0.8
    scene = unlit(Plane((edge_x, -10.0, 2.0), (1, 0, 0), (0, 1, 0), (20.0, 20.0), color=WHITE))
    cams = camera(dist=dist)
    view = render(scene, cams, supersample=8)
    grey = view.image.pixels[..., 0].astype(np.float64)
    rendered_edge = (1.0 - grey).sum(axis=1) - 0.5  # area left of the edge, pixel centres at integers
    line = np.c_[np.full(4001, edge_x), np.linspace(-3.0, 3.0, 4001), np.full(4001, 2.0)]
    projected = opencv_pixels(line, cams)
    predicted_edge = np.interp(np.arange(H), projected[:, 1], projected[:, 0])
    assert np.ptp(predicted_edge) > 2.0  # the lens really bends the line ...
    rows = slice(2, H - 2)
    np.testing.assert_allclose(rendered_edge[rows], predicted_edge[rows], atol=0.08)  # ... and we follow it
    # the undistorted camera renders the same line straight
    straight = render(scene, camera(), supersample=8).image.pixels[..., 0].astype(np.float64)
    assert np.ptp((1.0 - straight).sum(axis=1)) < 0.1


def test_a_distortion_that_folds_over_inside_the_image_is_refused():
    scene = unlit(Sphere((0.0, 0.0, 3.0), 0.5, color=WHITE))
    with pytest.raises(InvalidValue, match="folds over") as info:
        render(scene, camera(dist=np.array([0.0, 0.0, 0.0, 0.0, -5.0]), K=np.array([[20.0, 0, 47.5],
                                                                                    [0, 20.0, 35.5], [0, 0, 1]])))
    assert info.value.field == "dist"


# --- anti-aliasing ------------------------------------------------------------------------------------------------
def test_supersampled_colour_is_the_mean_of_the_samples():
    """Supersampling s = 2 equals rendering at twice the resolution (K scaled about the pixel grid) and averaging."""
    scene = Scene((Sphere((0.0, 0.0, 3.0), 0.8, texture=np.random.default_rng(0).uniform(0, 1, (32, 64, 3))),
                   Box((0.8, 0.5, 2.5), (0.5, 0.5, 0.5), color=(0.9, 0.5, 0.1))), background=(0.1, 0.2, 0.3))
    R = rotvec_to_matrix(np.array([0.05, -0.1, 0.0]))
    cams = camera(R=R, dist=DIST)
    K_fine = K.copy()
    K_fine[:2] *= 2.0
    K_fine[:2, 2] += 0.5
    fine = render(scene, camera(R=R, K=K_fine, dist=DIST, width=2 * W, height=2 * H), supersample=1)
    coarse = render(scene, cams, supersample=2)
    mean = fine.image.pixels.reshape(H, 2, W, 2, 3).mean(axis=(1, 3))
    # the mip level differs (the fine render's samples are its pixels), so compare away from textures
    untextured = render(scene, cams, supersample=1).object_ids != 0
    np.testing.assert_allclose(coarse.image.pixels[untextured], mean[untextured], atol=1e-5)
    # and the depth of the coarse view is the fine view's at the matching pixel centres (2u + 0.5 -> no sample)
    np.testing.assert_allclose(render(scene, cams, supersample=1).depth[coarse.mask], coarse.depth[coarse.mask])


def test_anti_aliased_edge_coverage_matches_the_covered_area():
    """A vertical white edge at a known sub-pixel position: each pixel's grey is the covered fraction (1/s steps)."""
    edge_u = 40.3  # in pixels, between pixel centres 40 and 41
    x = (edge_u - K[0, 2]) / K[0, 0]
    scene = unlit(Plane((x * 2.0, -10.0, 2.0), (1, 0, 0), (0, 1, 0), (20.0, 20.0), color=WHITE))
    view = render(scene, camera(), supersample=8)
    row = view.image.pixels[H // 2, :, 0]
    assert row[:40].max() == 0.0 and row[41:].min() == 1.0
    np.testing.assert_allclose(row[40], 0.25, atol=1e-6)  # samples at 40 + (i + 0.5)/8 - 0.5 right of 40.3: 2 of 8


# --- meshes -------------------------------------------------------------------------------------------------------
def box_mesh(size, center) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=size)
    mesh.apply_translation(center)
    return mesh


@pytest.mark.parametrize("intersector", ["numpy", "auto"])
def test_a_mesh_box_renders_like_the_box_primitive(intersector):
    R = rotvec_to_matrix(np.array([0.3, 0.4, 0.1]))
    t = np.array([0.0, 0.0, 3.0])
    size, center = (1.0, 0.7, 0.5), (0.1, 0.0, 0.2)
    primitive = render(unlit(Box(center, size, color=WHITE)), camera(R, t), supersample=1)
    mesh = render(unlit(MeshObject(box_mesh(size, center), color=WHITE, intersector=intersector)), camera(R, t),
                  supersample=1)
    agree = primitive.mask == mesh.mask
    assert agree.mean() > 0.995  # only silhouette pixels may differ (edges shared by two triangles)
    both = primitive.mask & mesh.mask
    np.testing.assert_allclose(mesh.depth[both], primitive.depth[both], rtol=1e-12)


def test_embree_and_moller_trumbore_agree_when_embree_is_installed():
    mesh = trimesh.creation.torus(major_radius=0.5, minor_radius=0.2)
    cams = camera(rotvec_to_matrix(np.array([1.0, 0.0, 0.0])), np.array([0.0, 0.0, 2.0]))
    reference = render(unlit(MeshObject(mesh, color=WHITE, intersector="numpy")), cams, supersample=1)
    auto = render(unlit(MeshObject(mesh, color=WHITE)), cams, supersample=1)
    assert (reference.mask != auto.mask).mean() < 0.005
    both = reference.mask & auto.mask
    np.testing.assert_allclose(auto.depth[both], reference.depth[both], rtol=1e-9)
    if not _embree_available():
        with pytest.raises(InvalidValue, match="embreex"):
            MeshObject(mesh, intersector="embree")


def test_moller_trumbore_known_hits():
    triangles = np.array([[[0.0, 0.0, 2.0], [1.0, 0.0, 2.0], [0.0, 1.0, 2.0]],
                          [[0.0, 0.0, 3.0], [1.0, 0.0, 3.0], [0.0, 1.0, 3.0]]])
    directions = np.array([[0.2, 0.2, 1.0], [0.9, 0.9, 1.0], [0.1, 0.1, -1.0], [0.3, 0.3, 2.0]])
    s, face = moller_trumbore(np.zeros(3), directions, triangles)
    np.testing.assert_allclose(s, [2.0, np.inf, np.inf, 1.0])
    np.testing.assert_array_equal(face, [0, -1, -1, 0])


@pytest.mark.parametrize("spread", [1.0, 3.0])  # 3: some triangles reach behind the rays' origin
def test_binned_moller_trumbore_equals_the_brute_force_test(spread):
    rng = np.random.default_rng(int(spread))
    triangles = rng.uniform(-spread, spread, (200, 3, 3)) + [0.0, 0.0, 4.0 if spread == 1.0 else 0.0]
    directions = np.c_[rng.uniform(-0.4, 0.4, (3000, 2)), np.ones(3000)]
    brute = moller_trumbore(np.zeros(3), directions, triangles)
    binned = binned_moller_trumbore(np.zeros(3), directions, triangles, cells=8)
    assert np.isfinite(brute[0]).mean() > 0.3
    np.testing.assert_array_equal(binned[0], brute[0])
    np.testing.assert_array_equal(binned[1], brute[1])


def test_mesh_vertex_colours_and_uv_textures_are_used():
    mesh = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=np.tile([255, 0, 0, 255], (8, 1)))
    view = render(unlit(MeshObject(mesh)), camera(t=np.array([0.0, 0.0, 3.0])), supersample=1)
    np.testing.assert_allclose(view.image.pixels[H // 2, W // 2], (1.0, 0.0, 0.0), atol=1e-6)
    # a quad with UVs mapping the whole of a two-colour texture: left half black, right half white
    quad = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    texture = np.zeros((4, 8, 3))
    texture[:, 4:] = 1.0
    obj = MeshObject(quad, texture=texture, uv=[[0, 1], [1, 1], [1, 0], [0, 0]])
    view = render(unlit(obj), camera(t=np.array([0.0, 0.0, 2.0])), supersample=1)
    quarter = int(K[0, 0] * 0.5 / 2.0)  # u = 1/4 and 3/4 of the texture lie 0.5 m left and right of the centre
    assert view.image.pixels[H // 2, int(K[0, 2]) - quarter, 0] < 0.02
    assert view.image.pixels[H // 2, int(K[0, 2]) + quarter + 1, 0] > 0.98


# --- lighting -------------------------------------------------------------------------------------------------------
def test_lambert_shading_depends_on_the_point_not_on_the_view():
    plane = Plane.centered((0.0, 0.0, 0.0), (1, 0, 0), (0, 1, 0), (4.0, 4.0), color=(0.8, 0.8, 0.8))
    scene = Scene((plane,), light=(0.0, 0.6, 0.8), ambient=0.25)
    expected = 0.8 * (0.25 + 0.75 * 0.8)
    for eye in ([0.0, 0.0, 3.0], [1.0, -1.0, 2.0], [0.0, 0.0, -3.0]):  # the last sees the back: it is lit less
        R, t = look_at(np.array(eye), np.zeros(3), (0.0, 1.0, 0.0))
        pixel = render(scene, camera(R, t), supersample=1).image.pixels[H // 2, W // 2]
        np.testing.assert_allclose(pixel, expected if eye[2] > 0 else 0.8 * 0.25, atol=1e-6)


# --- textures -------------------------------------------------------------------------------------------------------
def test_texture_sampling_at_texel_centres_returns_the_texels_and_wraps():
    image = np.random.default_rng(3).uniform(0, 1, (8, 16, 3)).astype(np.float32)
    texture = Texture(image)
    rows, columns = np.meshgrid(np.arange(8), np.arange(16), indexing="ij")
    uv = np.stack([(columns.ravel() + 0.5) / 16, (rows.ravel() + 0.5) / 8], axis=1)
    np.testing.assert_allclose(texture.sample(uv), image.reshape(-1, 3), atol=1e-4)
    np.testing.assert_allclose(texture.sample(uv + [3.0, -2.0]), image.reshape(-1, 3), atol=1e-4)
    np.testing.assert_allclose(texture.sample([[0.0, 0.5 / 8]])[0], 0.5 * (image[0, 0] + image[0, -1]), atol=1e-4)


def test_texture_minification_averages_instead_of_aliasing():
    stripes = np.zeros((64, 64, 3), dtype=np.float32)
    stripes[:, ::2] = 1.0
    texture = Texture(stripes)
    uv = np.random.default_rng(0).uniform(0, 1, (500, 2))
    np.testing.assert_allclose(texture.sample(uv, np.full(500, 1.0)), 0.5, atol=0.02)  # one sample = the whole tile
    assert texture.sample(uv, np.full(500, 1.0 / 64)).std() > 0.2  # at full resolution the stripes remain


def test_textures_accept_uint8_and_grey_and_reject_bad_shapes():
    assert Texture(np.full((4, 4), 255, dtype=np.uint8)).image.shape == (4, 4, 3)
    with pytest.raises(InvalidValue, match="RGB"):
        Texture(np.zeros((4, 4, 2)))
    with pytest.raises(InvalidValue, match="2 x 2"):
        Texture(np.zeros((1, 4, 3)))


# --- errors ---------------------------------------------------------------------------------------------------------
def test_bad_camera_index_names_the_range():
    scene = unlit(Sphere((0.0, 0.0, 3.0), 0.5))
    for index in (1, -2, 1.0, True):
        with pytest.raises(InvalidValue, match="out of range") as info:
            render(scene, camera(), index)
        assert info.value.field == "index" and "1 cameras" in info.value.reason
    np.testing.assert_array_equal(render(scene, camera(), -1, supersample=1).depth,
                                  render(scene, camera(), 0, supersample=1).depth)


def test_bad_render_arguments_are_refused_clearly():
    scene = unlit(Sphere((0.0, 0.0, 3.0), 0.5))
    for supersample in (0, 9, 2.0):
        with pytest.raises(InvalidValue, match="supersample"):
            render(scene, camera(), supersample=supersample)
    with pytest.raises(InvalidValue, match="Cameras"):
        render(scene, "camera")
    with pytest.raises(InvalidValue, match="Scene"):
        render([scene], camera())


def test_bad_objects_are_refused_clearly():
    with pytest.raises(InvalidValue, match="perpendicular"):
        Plane((0, 0, 0), (1, 0, 0), (1, 1, 0), (1.0, 1.0))
    with pytest.raises(InvalidValue, match="positive"):
        Box((0, 0, 0), (1.0, -1.0, 1.0))
    with pytest.raises(InvalidValue, match="rotation"):
        Box((0, 0, 0), (1.0, 1.0, 1.0), rotation=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(InvalidValue, match="positive"):
        Sphere((0, 0, 0), 0.0)
    with pytest.raises(InvalidValue, match="trimesh"):
        MeshObject("bunny.obj")
    with pytest.raises(InvalidValue, match="uv"):
        MeshObject(trimesh.creation.box(), texture=np.zeros((4, 4, 3)), uv=np.zeros((3, 2)))
    with pytest.raises(InvalidValue, match="colour"):
        Sphere((0, 0, 0), 1.0, color=(2.0, 0.0, 0.0))
    with pytest.raises(InvalidValue, match="object 0"):
        Scene(("sphere",))


def test_scene_bounds_enclose_every_object():
    scene = Scene((Sphere((1.0, 2.0, 3.0), 0.5), Box((-1.0, 0.0, 0.0), (2.0, 2.0, 2.0))))
    lower, upper = scene.bounds()
    np.testing.assert_allclose(lower, [-2.0, -1.0, -1.0])
    np.testing.assert_allclose(upper, [1.5, 2.5, 3.5])
