"""``edit``'s local edit (issue 35) from its flags --local, --region, --masks (declared in
:class:`experiments.edit.EditCommand`)."""

from __future__ import annotations

from pathlib import Path


def local_spec(args, config, data):
    """The run's :class:`jaxedit.edit.local.LocalSpec` from the flags (None: a global edit).

    ``config``: the EditRunConfig (its downscale reads the frames as the run does);
    ``data``: the run's EditData (the masks are matched to its training views).
    """
    from jaxedit.edit import local as L

    regions = tuple(L.parse_region(r) for r in getattr(args, "region", []) or [])
    masks = None
    if getattr(args, "masks", None) is not None:
        import numpy as np

        from jaxedit.io import load_nerfstudio
        from jaxedit.io.nerfstudio import dataset_downscale

        dataset = load_nerfstudio(args.data, downscale=dataset_downscale(args.data,
                                                                         config.downscale),
                                  skip_missing=config.skip_missing_images)
        names = [dataset.filenames[i] for i in np.asarray(dataset.train_indices)]
        masks = L.load_masks(args.masks, names, tuple(data.train_images.shape[1:3]),
                             originals=_photo_names(dataset.path, names))
    spec = L.LocalSpec(mode=getattr(args, "local", "off"), regions=regions, masks=masks)
    return spec if spec.active else None


def _photo_names(transforms, names: list[str]) -> list[str | None]:
    """Each frame's own photo (``original_file_path``, kept by process-data) or None."""
    import json

    frames = json.loads(Path(transforms).read_text()).get("frames", [])
    photo = {f.get("file_path"): f.get("original_file_path") for f in frames
             if isinstance(f, dict)}
    return [photo.get(n) for n in names]
