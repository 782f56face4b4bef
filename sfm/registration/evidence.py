"""Evidence for every placement: how each camera was placed, what confirmed it, and the verdict (docs/trust.md).

A camera's verdict:

- ``verified``: in model 0, placed by evidence (pairs the filter verified at its thresholds, 2D-3D inliers, shared
  points), and every join that carried it into model 0 confirmed;
- ``own_model``: the same, in a model of its own (no confirmed join reaches model 0);
- ``approximate``: placed by a join nothing confirms (a guessed scale or length: ``unconfirmed_joins:
  approximate``). Approximate cameras stay out of densify and the exports.

A join is confirmed when shared points (``registration.min_merge_points`` or more, or ``min_join_points`` for
parts of one averaged layout), independent 2D-3D resections, a second independent pair, or the camera height above
the floor (a tripod keeps it) agree with it and fix its scale; one that rests on a guessed scale or length (one pair
alone, or pairs that touch one camera of a side, with no floor to measure them) is not.
Pure bookkeeping: no file access.
"""

from __future__ import annotations

import numpy as np

VERDICTS = ("verified", "approximate", "own_model")


def placements(*, names: list[str], model_id: np.ndarray, own: dict[int, dict], join_records: list[dict],
               approximate: np.ndarray, pairs: np.ndarray, weights: np.ndarray, pair_ok: np.ndarray) -> dict[str, dict]:
    """Per placed image (by name): {"how", "evidence", "joins", "scale", "verdict"} (see the module doc).

    own: image -> {"how": ..., evidence} (`models.ModelSet.own`); join_records: `ModelSet.join_records`; pairs (P, 2)
    with weights (P,) (inliers of the pairs registration used, 0 for the others) and pair_ok (P,) (consistent in
    one model)."""
    used = pair_ok & (weights > 0)
    out = {}
    for k in np.flatnonzero(model_id >= 0):
        k = int(k)
        touching = used & (pairs == k).any(axis=1)
        order = np.flatnonzero(touching)[np.argsort(-weights[touching], kind="stable")]
        verified = [[names[int(pairs[p, 1] if pairs[p, 0] == k else pairs[p, 0])], int(weights[p])] for p in order]
        record = dict(own.get(k, {"how": "averaging"}))
        how = record.pop("how")
        if "pair" in record:
            record["pair"] = [names[record["pair"][0]], record["pair"][1]]
        joins = [_join_text(j, names) for j in join_records if k in j["images"]]
        guessed = bool(approximate[k]) or any(not j["confirmed"] for j in joins)
        verdict = "approximate" if guessed else ("verified" if model_id[k] == 0 else "own_model")
        out[names[k]] = {"how": how, "evidence": {"verified_pairs": verified, **record}, "joins": joins,
                         "scale": "guessed" if guessed else "measured", "verdict": verdict}
    return out


def _join_text(join: dict, names: list[str]) -> dict:
    evidence = dict(join["evidence"])
    if "pairs" in evidence:
        evidence["pairs"] = [[names[k], names[l], n] for k, l, n in evidence["pairs"]]
    return {"kind": join["kind"], "confirmed": join["confirmed"], "confirmed_by": confirmed_by(join),
            "scale": join["scale"], "evidence": evidence}


def confirmed_by(join: dict) -> str:
    """What confirmed a join, in words ("nothing: ..." when nothing did)."""
    e = join["evidence"]
    if not join["confirmed"]:
        return "nothing: its scale and length are guesses"
    if "camera_height" in e:
        h = e["camera_height"]
        joined = "one camera" if h["joined"] is None else f"{h['joined']} in its own model"
        return (f"the camera height above the floor ({h['model']} in the model's units, {joined}) sets its scale"
                + (" and the floor below the pair's cameras its length" if len(e.get("pairs", [])) == 1 else ""))
    if "points" in e:
        return f"{e['points']} shared points fit both sides"
    if "tracks" in e:
        return f"{e['tracks']} shared tracks agree on its scale"
    if "resected" in e:
        return f"{e['resected']} of its images resected into the model on their own"
    if "pairs" in e:
        return f"{len(e['pairs'])} pairs agree on its rotation and place both sides"
    return join["kind"]


def verdict_counts(records: dict[str, dict], num_images: int) -> dict[str, int]:
    """{"verified": n, "approximate": n, "own_model": n, "unregistered": n}."""
    counts = {v: 0 for v in VERDICTS}
    for r in records.values():
        counts[r["verdict"]] += 1
    counts["unregistered"] = num_images - len(records)
    return counts


def verified_mask(names: list[str], records: dict[str, dict]) -> np.ndarray:
    """(N,) images placed in some model and not approximate."""
    return np.array([records.get(n, {}).get("verdict") in ("verified", "own_model") for n in names], bool)


def weakest_links(records: dict[str, dict], toward_main: dict[int, list[tuple[str, str, int, int]]],
                  count: int = 5) -> list[dict]:
    """The links a user can strengthen, weakest first, each {"link", "evidence", "confirm"}: approximate joins (the
    pair they rest on), separate models (their best pairs toward model 0: `toward_main`, model -> [(image of the
    model, image of model 0, raw matches, inliers)]), the joins only the camera height confirms, then the verified
    cameras with the least evidence (one verified pair)."""
    out, seen = [], set()
    for name, r in records.items():
        for j in r["joins"]:
            if j["confirmed"]:
                continue
            pair = (j["evidence"].get("pairs") or [[name, "?", 0]])[0]
            key = (j["kind"], pair[0], pair[1])
            if key in seen:
                continue
            seen.add(key)
            out.append({"link": f"{pair[0]} – {pair[1]}", "evidence": f"{j['kind']} ({pair[2]} inliers); "
                        f"{j['confirmed_by']}", "confirm": f"8 hand points on {pair[0]} / {pair[1]}"})
    for m, found in sorted(toward_main.items()):
        if not found:
            continue
        a, b, raw, inliers = found[0]
        out.append({"link": f"model {m} – model 0 at {a} – {b}",
                    "evidence": f"{raw} raw matches, {inliers} inliers: too few to verify alone",
                    "confirm": f"8 hand points on {a} / {b}"})
    for name, r in records.items():  # confirmed by the camera height alone: the tripod's word, no shared point
        for j in r["joins"]:
            pair = (j["evidence"].get("pairs") or [[name, "?", 0]])[0]
            key = (j["kind"], pair[0], pair[1])
            if not j["confirmed"] or "camera_height" not in j["evidence"] or key in seen:
                continue
            seen.add(key)
            out.append({"link": f"{pair[0]} – {pair[1]}", "evidence": f"{j['kind']} ({pair[2]} inliers)",
                        "confirm": f"8 hand points on {pair[0]} / {pair[1]}, or a panorama between them"})
    thin = sorted((len(r["evidence"]["verified_pairs"]), name) for name, r in records.items()
                  if r["verdict"] != "approximate" and len(r["evidence"]["verified_pairs"]) <= 1
                  and r["how"] == "averaging")
    for n, name in thin:
        pairs = records[name]["evidence"]["verified_pairs"]
        other = pairs[0][0] if pairs else "?"
        out.append({"link": f"{name}", "evidence": f"{n} verified pair" + (f" ({other}, {pairs[0][1]} inliers)"
                                                                          if pairs else ""),
                    "confirm": f"a panorama between {name} and {other}, or hand points on {name} / {other}"})
    return out[:count] if count else out


def verdict_line(summary: dict) -> str | None:
    """`status`'s line, e.g. "registration: 28 verified, 2 approximate, 2 in own models", from the registration
    summary (None when it holds no verdicts: a workspace from before they existed)."""
    v = summary.get("verdicts")
    if not v:
        return None
    rest = f", {v['unregistered']} in no model" if v.get("unregistered") else ""
    return (f"registration: {v['verified']} verified, {v['approximate']} approximate, {v['own_model']} in own "
            f"models{rest}")
