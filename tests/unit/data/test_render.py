import numpy as np

from occtrain.data.render import render_bev, top_down_classes
from occtrain.formats.occ3d import CLASS_COLORS, FREE, GRID_SHAPE


def test_top_down_takes_highest_occupied_voxel():
    sem = np.full(GRID_SHAPE, FREE, np.uint8)
    sem[5, 6, 0] = 11  # road below
    sem[5, 6, 3] = 4  # car above it
    sem[7, 7, 1] = 13
    top = top_down_classes(sem)
    assert top[5, 6] == 4 and top[7, 7] == 13 and top[0, 0] == FREE


def test_bev_orientation_forward_is_up_left_is_left():
    sem = np.full(GRID_SHAPE, FREE, np.uint8)
    sem[190:, 95:105, 0] = 4  # far ahead (+x)
    sem[95:105, 190:, 0] = 16  # far left (+y)
    img = np.asarray(render_bev(sem, scale=1))
    assert (img[3, 100] == CLASS_COLORS[4]).all()  # top row: ahead
    assert (img[100, 3] == CLASS_COLORS[16]).all()  # left column: left
