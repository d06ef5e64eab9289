"""Depth-ordered previews (lc_petsc.io.previews): a near strand overdraws a far one
whatever their order in the file, in every view; the head sphere hides strands behind
it and not those in front; rendered PNGs are not blank."""

import numpy as np
import pytest

from lc_petsc.io.previews import VIEW_AXES, VIEW_TOWARD, _draw, _pyplot, render_previews


def _render(x, offsets, view, head=None, limits=((-3, 3), (-3, 3))):
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(3, 3), dpi=100)
    _draw(ax, x, offsets, view, limits, head=head, lw=8.0)
    ax.set_axis_off()
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].astype(float) / 255.0

    def pixel(p):
        a, b = VIEW_AXES[view][:2]
        px, py = ax.transData.transform((p[a], p[b]))
        return img[int(round(img.shape[0] - py)), int(round(px))]
    plt.close(fig)
    return pixel


def _strand(p0, p1, n=9):
    return np.linspace(p0, p1, n)


@pytest.mark.parametrize("view", ["front", "side", "top"])
@pytest.mark.parametrize("near_first", [True, False])
def test_near_strand_overdraws_far_strand(view, near_first):
    a, b = VIEW_AXES[view][:2]
    toward = VIEW_TOWARD[view]
    ea, eb = np.eye(3)[a], np.eye(3)[b]
    near = _strand(-2 * ea + toward, 2 * ea + toward)          # along the screen's x, 1 cm nearer
    far = _strand(-2 * eb - toward, 2 * eb - toward)           # along the screen's y, 1 cm farther
    wisps = [near, far] if near_first else [far, near]
    pixel = _render(np.concatenate(wisps), np.array([0, 9, 18]), view)
    crossing = pixel(np.zeros(3))
    on_near, on_far = pixel(1.2 * ea), pixel(1.2 * eb)
    assert np.abs(on_near - on_far).max() > 0.1                 # the two are told apart
    assert np.abs(crossing - on_near).max() < 0.03, (crossing, on_near, on_far)
    assert np.abs(crossing - on_far).max() > 0.1


def test_far_strands_fade_into_the_background():
    x = np.concatenate([_strand([-2, 1, 1.0], [2, 1, 1.0]), _strand([-2, -1, -1.0], [2, -1, -1.0])])
    pixel = _render(x, np.array([0, 9, 18]), "front")
    background = pixel([0, 2.5, 0])
    assert np.abs(pixel([0, 1, 0]) - background).sum() > np.abs(pixel([0, -1, 0]) - background).sum() + 0.3


def test_head_hides_strands_behind_it_only():
    head = (np.zeros(3), 1.5)
    # pieces of 4 edges are hidden or shown whole: 41 vertices make 0.5 cm pieces
    behind = _strand([-2.5, 0.4, -2.0], [2.5, 0.4, -2.0], n=41)
    before = _strand([-2.5, -0.4, 2.0], [2.5, -0.4, 2.0], n=41)
    pixel = _render(np.concatenate([behind, before]), np.array([0, 41, 82]), "front", head=head)
    bare = _render(np.zeros((0, 3)), np.array([0]), "front", head=head)
    assert np.abs(pixel([0, 0.4, 0]) - bare([0, 0.4, 0])).max() < 0.03      # sphere, not strand
    assert np.abs(pixel([0, -0.4, 0]) - bare([0, -0.4, 0])).max() > 0.1     # strand over sphere
    assert np.abs(pixel([2.2, 0.4, 0]) - bare([2.2, 0.4, 0])).max() > 0.1   # beside the head: shown
    # the sphere is shaded: lit upper left, darker lower right
    assert bare([-0.7, 0.7, 0]).sum() > bare([0.7, -0.7, 0]).sum() + 0.3


def test_rendered_previews_not_blank(tmp_path):
    import h5py
    import matplotlib.image as mpimg
    from lc_petsc.scene import geometry
    x = np.concatenate([geometry.wisp4c(40, root=(2.0 * w, 15.0, 0.0), spin=w) for w in range(6)])
    with h5py.File(tmp_path / "frames.h5", "w") as f:
        f["positions"] = np.stack([x, x + [0.5, 0, 0]])
        f["time"] = [0.0, 0.1]
        f["wisp_offsets"] = np.arange(7) * 40
    paths = render_previews(tmp_path / "frames.h5", tmp_path, [0, -1], contact_panels=2,
                            head=lambda t: (np.zeros(3), 15.25))
    assert len(paths) == 3
    for p in paths:
        img = mpimg.imread(p)[..., :3]
        assert img.std() > 0.05
        colours = np.unique((img.reshape(-1, 3) * 255).astype(int), axis=0)
        assert len(colours) > 200           # shaded head and strands, not a flat plot


def test_no_preview_frames_and_no_contact_sheet_render_nothing(tmp_path):
    """``output.preview_frames = []`` with ``output.contact_sheet = 0`` asks for no image:
    the frame limits were taken over no frame (numpy's min of an empty list), and a
    finished run ended in "output error: previews ...: zero-size array" with exit
    status 3."""
    import h5py
    from lc_petsc.scene import geometry
    x = np.concatenate([geometry.wisp4c(40, root=(2.0 * w, 15.0, 0.0), spin=w) for w in range(2)])
    with h5py.File(tmp_path / "frames.h5", "w") as f:
        f["positions"] = np.stack([x, x + [0.5, 0, 0]])
        f["time"] = [0.0, 0.1]
        f["wisp_offsets"] = np.arange(3) * 40
    assert render_previews(tmp_path / "frames.h5", tmp_path, [], contact_panels=0) == []
    assert not (tmp_path / "previews").exists() and not (tmp_path / "contact_sheet.png").exists()
    # one panel of either kind still draws
    assert [p.rsplit("/", 1)[1] for p in render_previews(tmp_path / "frames.h5", tmp_path, [], 1)] \
        == ["contact_sheet.png"]


def test_a_preview_that_fails_mid_write_leaves_no_partial_png(tmp_path, monkeypatch):
    """A PNG is written aside and renamed when complete: a failure mid-write (a full
    disk) left the first bytes of the image at the preview's name, which a viewer showed
    until a restart rewrote it.  Now the image there is the last complete one (here an
    earlier call's) and nothing else is left."""
    import errno
    import os
    import h5py
    import matplotlib.image
    from lc_petsc.scene import geometry
    x = np.concatenate([geometry.wisp4c(40, root=(2.0 * w, 15.0, 0.0), spin=w) for w in range(3)])
    with h5py.File(tmp_path / "frames.h5", "w") as f:
        f["positions"] = np.stack([x, x + [0.5, 0, 0]])
        f["time"] = [0.0, 0.1]
        f["wisp_offsets"] = np.arange(4) * 40
    paths = render_previews(tmp_path / "frames.h5", tmp_path, [1], contact_panels=2)
    assert [p.rsplit("/", 1)[1] for p in paths] == ["frame_00001.png", "contact_sheet.png"]
    complete = {p: open(p, "rb").read() for p in paths}

    imsave = matplotlib.image.imsave        # what the Agg canvas's print_png writes with

    def full_disk(target, arr, **kw):
        if not isinstance(target, (str, os.PathLike)):     # bbox_inches="tight"'s dry run
            return imsave(target, arr, **kw)
        with open(target, "wb") as fh:      # the header made it, the rest did not
            fh.write(b"\x89PNG\r\n\x1a\n" + b"\0" * 100)
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(matplotlib.image, "imsave", full_disk)
    with pytest.raises(OSError, match="No space left"):
        render_previews(tmp_path / "frames.h5", tmp_path, [1], contact_panels=2)
    for p, data in complete.items():
        assert open(p, "rb").read() == data
    assert sorted(p.name for p in (tmp_path / "previews").iterdir()) == ["frame_00001.png"]
    assert not any(p.name.endswith(".tmp") for p in tmp_path.iterdir())
