"""COCO keypoint JSON: ``images`` (id, file_name), ``annotations`` (image_id, keypoints
[x0, y0, v0, ...]) and ``categories`` (keypoints names, 1-based skeleton).

The third value is read as a score: 0 = missing, values above 1 (COCO's visibility flag 2)
count as 1. Keys are the images' ``file_name``s, matched by ``base.match_names``; images
without annotations get no people.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from .base import LAYOUTS, Keypoints, Layout, as_points, get_layout, read_json, stack_people


def _category_layout(category: dict, path: Path) -> Layout | None:
    names = category.get("keypoints")
    if not isinstance(names, list) or not names:
        return None
    names = [str(n) for n in names]
    if names == LAYOUTS["COCO_17"].point_names:
        return LAYOUTS["COCO_17"]
    try:
        edges = [(int(a) - 1, int(b) - 1) for a, b in category.get("skeleton", [])]
    except (TypeError, ValueError):
        raise InputError(f"{path}: category '{category.get('name')}' has a bad skeleton") from None
    left = [(i, n) for i, n in enumerate(names) if n.startswith("left_")]
    index = {n: i for i, n in enumerate(names)}
    pairs = [(i, index[n.replace("left_", "right_", 1)]) for i, n in left
             if n.replace("left_", "right_", 1) in index]
    return Layout(name=str(category.get("name", "coco")), point_names=names, edges=edges,
                  symmetric_pairs=pairs)


def read(path: Path, *, layout: str | Layout | None = None, category: str | None = None
         ) -> Keypoints:
    """Read a COCO keypoint file; ``category`` picks one when several have keypoints;
    ``layout`` overrides the category's names and skeleton."""
    data = read_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("images"), list) \
            or not isinstance(data.get("annotations"), list):
        raise InputError(f"{path}: not a COCO keypoint file (needs 'images' and 'annotations')")
    categories = {c.get("id"): c for c in data.get("categories", []) if isinstance(c, dict)
                  and c.get("keypoints")}
    if category is not None:
        categories = {k: c for k, c in categories.items() if c.get("name") == category}
        if not categories:
            raise InputError(f"{path}: no keypoint category named '{category}'")
    if len(categories) > 1:
        names = ", ".join(str(c.get("name")) for c in categories.values())
        raise InputError(f"{path}: several keypoint categories ({names}); choose one by name")
    cat_id, cat = next(iter(categories.items()), (None, {}))
    annotations = [a for a in data["annotations"] if isinstance(a, dict)
                   and (cat_id is None or a.get("category_id", cat_id) == cat_id)]
    if cat:
        num_points = len(cat["keypoints"])
    elif annotations and isinstance(annotations[0].get("keypoints"), list):
        num_points = len(annotations[0]["keypoints"]) // 3
    else:
        raise InputError(f"{path}: no keypoint category and no annotation to size the points")
    if layout is None:
        layout = _category_layout(cat, path) if cat else None
    layout = get_layout(layout, num_points, path)
    names: dict[object, str] = {}
    for i, im in enumerate(data["images"]):
        if not isinstance(im, dict) or "id" not in im or not isinstance(im.get("file_name"), str):
            raise InputError(f"{path}: images[{i}] needs 'id' and 'file_name'")
        names[im["id"]] = im["file_name"]
    people: dict[str, list] = {name: [] for name in names.values()}
    for i, ann in enumerate(annotations):
        source = f"{path} annotation {ann.get('id', i)}"
        if ann.get("image_id") not in names:
            raise InputError(f"{source}: image_id {ann.get('image_id')!r} not in 'images'")
        kp = as_points(ann.get("keypoints"), num_points, source)
        kp[:, 2] = kp[:, 2].clip(max=1.0)
        people[names[ann["image_id"]]].append(kp)
    points = {name: stack_people(v, num_points) for name, v in people.items()}
    return Keypoints(layout=layout, points=points, source=path)
