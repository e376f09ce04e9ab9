"""COCO keypoint JSON: ``images`` (id, file_name), ``annotations`` (image_id, keypoints
[x0, y0, v0, ...]) and ``categories`` (keypoints names, 1-based skeleton).

The third value is read as a score: 0 = missing, values above 1 (COCO's visibility flag 2)
count as 1. Keys are the images' ``file_name``s, matched by ``base.match_names``; images
without annotations get no people.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from .base import (
    Keypoints,
    Layout,
    as_points,
    brief,
    expect,
    get_layout,
    index_pairs,
    known_layout,
    point_names,
    read_json,
    shown,
    stack_people,
)


def _category_layout(category: dict, names: list[str], where: str) -> Layout:
    known = known_layout(names)
    if known is not None:
        return known
    edges = index_pairs(category.get("skeleton", []), len(names), f"{where} 'skeleton'", base=1)
    index = {n: i for i, n in enumerate(names)}
    pairs = [(i, index[n.replace("left_", "right_", 1)]) for i, n in enumerate(names)
             if n.startswith("left_") and n.replace("left_", "right_", 1) in index]
    name = category.get("name")
    return Layout(name=str(name) if isinstance(name, (str, int, float)) else "coco",
                  point_names=names, edges=edges, symmetric_pairs=pairs)


def read(path: Path, *, layout: str | Layout | None = None, category: str | None = None
         ) -> Keypoints:
    """Read a COCO keypoint file; ``category`` picks one when several have keypoints;
    ``layout`` overrides the category's names and skeleton. A category naming the points of a
    known layout (COCO_17, HALPE_26, COCO-WholeBody's 133, ...; ``base.known_layout``) gets
    that layout."""
    data = read_json(path)
    where = shown(path)
    if not isinstance(data, dict) or "images" not in data or "annotations" not in data:
        raise InputError(f"{where}: not a COCO keypoint file (needs 'images' and 'annotations')")
    images = expect(data["images"], list, f"{where}: 'images'")
    annotations = expect(data["annotations"], list, f"{where}: 'annotations'")
    categories = {}
    for i, c in enumerate(expect(data.get("categories", []), list, f"{where}: 'categories'")):
        if isinstance(c, dict) and c.get("keypoints"):
            key = c.get("id")
            if key is not None:
                expect(key, (int, str), f"{where}: categories[{i}] 'id'")
            categories[key] = c
    if category is not None:
        categories = {k: c for k, c in categories.items() if c.get("name") == category}
        if not categories:
            raise InputError(f"{where}: no keypoint category named {brief(category)}")
    if len(categories) > 1:
        names = ", ".join(brief(c.get("name")) for c in categories.values())
        raise InputError(f"{where}: several keypoint categories ({names}); choose one by name")
    cat_id, cat = next(iter(categories.items()), (None, {}))
    annotations = [a for a in annotations if isinstance(a, dict)
                   and (cat_id is None or a.get("category_id", cat_id) == cat_id)]
    if cat:
        cat_where = f"{where}: category {brief(cat.get('name'))}"
        names = point_names(cat["keypoints"], f"{cat_where} 'keypoints'")
        num_points = len(names)
        if layout is None:
            layout = _category_layout(cat, names, cat_where)
    elif annotations and isinstance(annotations[0].get("keypoints"), list):
        num_points = len(annotations[0]["keypoints"]) // 3
    else:
        raise InputError(f"{where}: no keypoint category and no annotation to size the points")
    layout = get_layout(layout, num_points, path)
    names_by_id: dict[int | str, str] = {}
    for i, im in enumerate(images):
        if not isinstance(im, dict) or "id" not in im or not isinstance(im.get("file_name"), str):
            raise InputError(f"{where}: images[{i}] needs 'id' and 'file_name'")
        image_id = expect(im["id"], (int, str), f"{where}: images[{i}] 'id'")
        if image_id in names_by_id:
            raise InputError(f"{where}: images[{i}] repeats image id {brief(image_id)}")
        names_by_id[image_id] = im["file_name"]
    people: dict[str, list] = {name: [] for name in names_by_id.values()}
    for i, ann in enumerate(annotations):
        source = f"{where} annotation {brief(ann.get('id', i))}"
        image_id = expect(ann.get("image_id"), (int, str), f"{source}: 'image_id'")
        if image_id not in names_by_id:
            raise InputError(f"{source}: image_id {brief(image_id)} not in 'images'")
        kp = as_points(ann.get("keypoints"), num_points, source)
        kp[:, 2] = kp[:, 2].clip(max=1.0)
        people[names_by_id[image_id]].append(kp)
    points = {name: stack_people(v, num_points) for name, v in people.items()}
    return Keypoints(layout=layout, points=points, source=path)
