"""`name`'s safeguards against a confident wrong name: the adequacy test of
the named model (piecewise-linear hats of every state and input on the
equations the named candidates act on) and sets only for rivals the data
cannot separate."""

from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np
from helpers import compiled_programs
from test_discover import _dyn, _meas, B, PRIOR, Q, R, SPRING, T


def _simulate(seed: int, one_sided: float, contact: float = 0.0, states=None):
    """Oscillator data with damping on positive velocities only (a kink at
    rest that no candidate of the mechanical library has), or a contact
    spring beyond p = 10; the true states go to `states` if given."""
    import eqsmooth.discover as dc

    rng = np.random.default_rng(seed)
    x = np.stack([rng.normal(0, PRIOR[0], B), rng.normal(0, PRIOR[1], B)], 1)
    xs = []
    for _ in range(T):
        xs.append(x.copy())
        p, v = x[:, 0], x[:, 1]
        a = -SPRING * p - one_sided * v * (v > 0) - contact * np.maximum(p - 10, 0)
        x = np.stack([p + v, v + a], 1) + rng.normal(size=(B, 2)) * Q
    if states is not None:
        states.append(np.stack(xs, 1))
    y = np.stack(xs, 1)[..., :1] + R * rng.normal(size=(B, T, 1))
    init = np.concatenate([y, np.zeros_like(y)], -1)
    return dc.Sequences(y, np.zeros((B, 2)), initial_states=init)


def _model():
    import eqsmooth.discover as dc

    library = dc.mechanical_library([0], [1], 2, measured_positions=[0])
    return dc.ChainModel(
        _dyn, _meas, jnp.asarray(SPRING), Q, np.array([R]), PRIOR, library
    )


def test_hats_are_a_partition_of_unity():
    from eqsmooth.discover._adequacy import hat

    knots = np.array([-1.0, -0.2, 0.1, 0.5, 2.0])
    s = np.concatenate([np.linspace(-3.0, 3.0, 61), knots])
    w = np.stack([hat(s, knots, b)[0] for b in range(5)], 1)  # (points, hats)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-12)
    assert w.min() >= 0.0 and w.max() <= 1.0
    np.testing.assert_allclose(w[-5:], np.eye(5), atol=1e-12)  # 1 at its knot
    # The slopes are those of the pieces (central differences off the knots).
    s = np.linspace(-2.9, 2.9, 57)
    for b in range(5):
        up, down = hat(s + 1e-6, knots, b)[0], hat(s - 1e-6, knots, b)[0]
        np.testing.assert_allclose(hat(s, knots, b)[1], (up - down) / 2e-6, atol=1e-6)


def test_out_of_library_effect_is_partial_and_reuses_the_program():
    import eqsmooth.discover as dc

    model = _model()
    data = _simulate(1, 0.1)
    found = dc.find(model, data)
    named = dc.name(found, data)
    # The nearest smooth candidate (viscous damping) absorbs part of the
    # one-sided damping and is named, but not confidently: the hats of the
    # velocity on the velocity equation still score.
    assert named["named"], named["verdict"]
    assert named["alarms"]["partial"], named["adequacy"]
    assert named["verdict"].startswith("partial: "), named["verdict"]
    where = named["adequacy"]["where"]
    assert (where["equation"], where["variable"]) == ("x1'", "x1"), where
    assert named["adequacy"]["p_value"] < 1e-3
    # Another data set has other knots; they are data, not structure.
    other = _simulate(2, 0.1)
    with compiled_programs() as names:
        named2 = dc.name(dc.find(model, other), other)
    assert named2["adequacy"]["tested"]
    assert names == [], names


def test_find_localises_a_contact_spring():
    # A contact spring beyond p = 10 acts on the velocity equation only
    # there: `find(..., localise=True)` names the block (the position on the
    # velocity equation) and a region that covers p >= 10 and little else.
    import eqsmooth.discover as dc

    states = []
    data = _simulate(0, 0.0, contact=0.02, states=states)
    found = dc.find(_model(), data, localise=True)
    assert found["detected"]
    best = found["where"]["where"]
    assert (best["variable"], best["equation"]) == ("x0", "x1'"), best
    ((lo, hi),) = best["region"]
    assert hi is None and 3.0 < lo < 10.0, best["region"]
    p = states[0][..., 0]
    flagged, true = p >= lo, p >= 10.0
    precision = np.sum(flagged & true) / np.sum(flagged)
    recall = np.sum(flagged & true) / np.sum(true)
    assert precision > 0.8 and recall == 1.0, (precision, recall)
    # Without localise (the default) there is no region, and null data
    # (nothing detected) gets none either.
    assert "where" not in dc.find(_model(), data)
    null = _simulate(0, 0.0)
    assert "where" not in dc.find(_model(), null, localise=True)


def test_a_rival_the_data_can_separate_makes_no_set():
    from eqsmooth.discover._name import _classify_rivals, _verdict

    names = ["a", "b", "c"]
    # a and b: uncorrelated and well informed (expected gap 50 at c_a = 1);
    # a and c: perfectly correlated (no data of this kind separates them).
    info = np.array([[100.0, 0.0, 100.0], [0.0, 100.0, 0.0], [100.0, 0.0, 100.0]])
    out = {
        "steps": [{"best": "a"}],
        "equivalence_sets": [],
        "ambiguous": [],
        "named": ["a"],
        "tentative": False,
    }
    best = SimpleNamespace(z=np.array([1.0, 0.0, 0.0]))
    data = SimpleNamespace(num_sequences=24, length=40)
    _classify_rivals(out, names, 0, [1, 2], info, 0.95, best, data)
    rivals = {r["name"]: r for r in out["steps"][0]["rivals"]}
    assert rivals["b"]["separable"] and np.isclose(rivals["b"]["expected_gap"], 50.0)
    assert not rivals["c"]["separable"] and rivals["c"]["sequences_to_separate"] is None
    assert out["equivalence_sets"] == [["a", "c"]] and out["ambiguous"] == []
    assert _verdict(out, False) == (
        "not identifiable from this data: {a ≡ c} "
        "(no amount of data of this kind separates them)"
    )
    # Weaker information: b is kept, with the sequences that would separate.
    weaker = info / 20.0  # expected gap 2.5 < ln 20
    out |= {"steps": [{"best": "a"}], "equivalence_sets": [], "ambiguous": []}
    _classify_rivals(out, names, 0, [1], weaker, 0.95, best, data)
    (rival,) = out["steps"][0]["rivals"]
    assert not rival["separable"]
    np.testing.assert_allclose(rival["sequences_to_separate"], 24 * np.log(20) / 2.5)
    assert out["ambiguous"] == [["a", "b"]]
    assert "(about 29 sequences of length 40 would separate them)" in _verdict(
        out, False
    )


def _driven_field(x, u, w2):
    return jnp.stack([x[1], -w2 * jnp.sin(x[0]) + u[0]])


def test_hat_scores_from_offsets_equal_those_of_the_augmented_model():
    """The adequacy test scores its hats through the nominal model's score
    program (`Offsets`: a term's value and slope at the MAP); the scores and
    the observed information equal those of the model with the hats added
    as candidates, on an integrator with rate terms, hats of a state and of
    an input, on a dynamics and a measurement equation."""
    import dataclasses

    from test_discover_integrator import _measure, DT, W2

    import eqsmooth.discover as dc
    from eqsmooth.discover import _adequacy as A
    from eqsmooth.discover._fit import evaluate

    library = dc.mechanical_library(
        [0],
        [1],
        2,
        dt=DT,
        num_inputs=1,
        measured_positions=[0],
        include=("viscous damping", "actuator gain", "sensor scale"),
        rate=True,
    )
    model = dc.ChainModel(
        dc.Integrator(_driven_field, DT),
        _measure,
        jnp.asarray(W2),
        np.array([0.05, 0.2]),
        np.array([0.3]),
        np.ones(2),
        library,
        coefficients=np.array([0.3, 0.5, 0.0]),
    )
    rng = np.random.default_rng(0)
    B, T = 3, 12
    u = rng.normal(size=(B, T, 1))
    data = dc.Sequences(rng.normal(size=(B, T, 1)), np.zeros((B, 2)), inputs=u)
    z = np.concatenate([np.asarray(model.coefficients), [0.1, -0.2, 0.0]])
    from eqsmooth.discover._model import map_states

    xhat = np.asarray(
        map_states(model, jnp.asarray(z), data, jnp.asarray(data.initial_states))
    )
    # Named: the actuator gain (velocity equation) and the sensor scale (y0).
    terms, where = A._hat_terms(model, data, xhat, [1, 2])
    blocks = {w["block"] for w in where}
    assert blocks == {
        f"{v} on {e}" for v in ("x0", "x1", "u0") for e in ("x1'", "y0")
    }, blocks
    ev = A._hat_evaluation(model, data, z, xhat, terms)

    # The same hats as candidates (knots fixed for this data set).
    def feature(term, knots, b):
        def f(x, uu):
            s = (x if term.source == "x" else uu)[term.index]
            k = jnp.asarray(knots)
            last = len(knots) - 1
            if b == 0:
                w = jnp.clip((k[1] - s) / (k[1] - k[0]), 0.0, 1.0)
            elif b == last:
                w = jnp.clip((s - k[-2]) / (k[-1] - k[-2]), 0.0, 1.0)
            else:
                up = (s - k[b - 1]) / (k[b] - k[b - 1])
                w = jnp.maximum(jnp.minimum(up, (k[b + 1] - s) / (k[b + 1] - k[b])), 0)
            dim = 2 if term.target == "dynamics" else 1
            return w * jnp.zeros(dim).at[term.row].set(1.0)

        return f

    hats = []
    for i, (t, w) in enumerate(zip(terms, where)):
        b = w["knots"].index(w["near"])
        hats.append(
            dc.Candidate(f"hat {i}", feature(t, w["knots"], b), target=t.target)
        )
    K, H = len(library), len(terms)
    augmented = dataclasses.replace(
        model,
        candidates=model.candidates + tuple(hats),
        coefficients=np.concatenate([model.coefficients, np.zeros(H)]),
    )
    za = np.concatenate([z[:K], np.zeros(H), z[K:]])
    scales = np.array([np.sqrt(np.mean(t.value**2)) for t in terms])
    scales = np.concatenate([np.ones(K), np.where(scales > 0, scales, 1.0)])
    test = K + np.arange(H)
    ref = evaluate(augmented, data, za, xhat, scales, test, at_map=True)
    np.testing.assert_allclose(ev.per_sequence, ref.per_sequence, rtol=1e-12)
    np.testing.assert_allclose(ev.scores, ref.scores[:, test], rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(
        ev.hessian, ref.hessian[np.ix_(test, test)], rtol=1e-5, atol=1e-6
    )
    assert np.abs(ev.scores).max() > 1e-3  # not a comparison of zeros
