"""benchmarks/study_table.py's target table: verdicts read from `evaluate`'s paired comparisons in the right
direction for higher- and lower-is-better metrics, the not-discriminating mark, the ablation column and the count
row. Oracle: a study written by hand, where each comparison's interval says which side wins."""
import json

from _bench_helpers import load_benchmark

study_table = load_benchmark("study_table.py")


def _cmp(mean, lo, hi):  # evaluate's "a vs b": the statistics of a - b over views
    return {"mean": mean, "lo": lo, "hi": hi, "n": 12}


def _summary(**means):
    return {k: {"mean": v, "lo": v, "hi": v, "n": 12} for k, v in means.items()}


def _write_pair(root, scene, painting, comparisons, runs, blind=None):
    ev = root / scene / painting / "evaluation"
    ev.mkdir(parents=True)
    data = {"runs": [{"name": n, "summary": s} for n, s in runs.items()],
            "anchors": [{"name": "no stylization", "summary": _summary(consistency_k1=0.1)}],
            "comparisons": comparisons, "not_discriminating": blind or {}}
    (ev / "evaluation.json").write_text(json.dumps(data))
    (root / scene / painting / "tlvg").mkdir()
    (root / scene / painting / "tlvg" / "metrics.json").write_text(json.dumps({"gaussians_input": 100}))


def test_target_table_reads_directions_marks_and_counts(tmp_path):
    tlvg = _summary(detail=0.7, detail_inside=0.4, consistency_k1=0.2)
    tlvg["gaussians"] = 120
    # pair one: tlvg's flow above abcgs's (higher is better: "tlvg vs abcgs" > 0), its Gram below (lower is
    # better: "tlvg vs abcgs" < 0), its chroma noise above the ablation's (a loss), flow level with the scene
    _write_pair(tmp_path, "fern", "starry_night", {
        "tlvg vs abcgs": {"flow_alignment": _cmp(0.10, 0.08, 0.12), "style_gram": _cmp(-0.05, -0.07, -0.03),
                          "chroma_noise": _cmp(0.02, -0.01, 0.05), "stroke_scales": _cmp(0.03, 0.01, 0.05)},
        "tlvg vs rgb": {"chroma_noise": _cmp(0.09, 0.07, 0.11)},
        "tlvg vs no stylization": {"flow_alignment": _cmp(0.01, -0.01, 0.03)},
    }, {"tlvg": tlvg, "abcgs": {}, "rgb": {}})
    # pair two: stored the other way round ("abcgs vs tlvg"), tlvg's flow below; flow not discriminating here
    tlvg2 = _summary(detail=0.5, consistency_k1=0.1)
    tlvg2["gaussians"] = 130
    _write_pair(tmp_path, "lego", "shipwreck", {
        "abcgs vs tlvg": {"flow_alignment": _cmp(0.04, 0.02, 0.06)},
        "tlvg vs rgb": {"chroma_noise": _cmp(-0.30, -0.40, -0.20)},
    }, {"tlvg": tlvg2, "abcgs": {}, "rgb": {}}, blind={"flow_alignment": "no stylization"})

    data = study_table.load(tmp_path)
    order = sorted(data)
    heads, rows = study_table.target_rows(tmp_path, data, order, "tlvg", "rgb")
    fern, lego = (dict(zip(heads, (r[h] for h in heads))) for r in rows)
    assert fern["flow vs abcgs"] == ("yes (+0.100)", "yes")
    assert fern["Gram vs abcgs"] == ("yes (+0.050)", "yes")  # lower Gram is the better side
    assert fern["chroma vs abcgs"] == ("tie (-0.020)", "tie")
    assert fern["chroma vs rgb"] == ("no (-0.090)", "no")
    assert fern["flow vs un-stylized"] == ("tie (+0.010)", "tie")
    assert fern["detail"][1] is True and fern["MV k1 / un-stylized"] == ("2.00", False)
    assert fern["detail inside"] == ("0.40", False) and lego["detail inside"] == ("-", None)  # the outline left out
    assert fern["Gaussians / input"] == ("1.20", True)
    assert lego["flow vs abcgs"] == ("no (-0.040) †", "no")  # b vs a read as a - b; the mark of a blind metric
    assert lego["chroma vs rgb"] == ("yes (+0.300)", "yes")
    assert lego["detail"][1] is False and lego["Gaussians / input"][1] is False
    assert study_table.count([fern["flow vs abcgs"][1], lego["flow vs abcgs"][1]]) == "1 yes / 0 tie / 1 no"
    assert study_table.count([fern["detail"][1], lego["detail"][1]]) == "1 of 2 within the limit"
    assert study_table.count([None, None]) == "-"
    # the paired table (--paired): the other run minus the base, judged in the metric's own direction
    idx = {k: i for i, k in enumerate(study_table.PAIRED)}
    against_tlvg = study_table.paired_rows(data, order, "tlvg", "abcgs")
    assert against_tlvg[0][idx["flow_alignment"]] == "worse -0.100"  # abcgs's flow 0.10 under tlvg's
    assert against_tlvg[0][idx["style_gram"]] == "worse +0.050"  # abcgs's Gram 0.05 above: worse
    assert against_tlvg[0][idx["chroma_noise"]] == "level -0.020"
    assert against_tlvg[0][idx["stroke_scales"]] == "better -0.030"  # abcgs's stroke measure nearer: lower is better
    assert against_tlvg[0][idx["detail"]] == "-"  # not compared
    assert against_tlvg[1][idx["flow_alignment"]] == "better +0.040"  # stored as "abcgs vs tlvg"
    assert study_table.paired_rows(data, order, "abcgs", "tlvg")[0][idx["style_gram"]] == "better -0.050"


def test_missed_targets_count_the_seven_by_their_rules(tmp_path):
    """The seven counted targets of one pair: the two flow targets need 'yes' (a tie misses), the three 'no worse
    than abcgs' targets take a tie, detail inside and k1 their limits, and an unmeasured target counts as missed;
    the missed ones are named with the figure that missed."""
    tlvg = _summary(detail=0.7, detail_inside=0.4, consistency_k1=0.2)
    _write_pair(tmp_path, "fern", "starry_night", {
        "tlvg vs abcgs": {"flow_alignment": _cmp(0.10, 0.08, 0.12), "style_gram": _cmp(-0.05, -0.07, -0.03),
                          "chroma_noise": _cmp(0.02, -0.01, 0.05)},
        "tlvg vs no stylization": {"flow_alignment": _cmp(0.01, -0.01, 0.03)},
    }, {"tlvg": tlvg, "abcgs": {}}, blind={"flow_alignment": "no stylization"})
    data = study_table.load(tmp_path)
    _, rows = study_table.target_rows(tmp_path, data, sorted(data), "tlvg", None)
    miss, met = study_table.missed(rows[0])
    assert met == 3  # flow vs abcgs, Gram, chroma noise (a tie is no worse)
    assert miss == ["flow vs un-stylized +0.010 †", "NNFM not measured", "detail inside 0.40", "k1 2.00x"]
