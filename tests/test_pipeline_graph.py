"""Frame graph: wiring by buffer names, ordering, errors, pruning, options, counters, gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from gpupro.pipeline import Pass, Pipeline, PipelineError

SCENE = {"base": jnp.arange(4, dtype=jnp.float32)}


def make_x(params, inputs, scene):
    """Toy source pass: x = base + 1, counting its elements."""
    return {"x": scene["base"] + 1.0}, {"elements": jnp.int32(scene["base"].size)}


def scale_x(params, inputs, scene):
    """y = scale * x: the differentiable toy pass."""
    return {"y": params["scale"] * inputs["x"]}


def combine(params, inputs, scene, *, power=1):
    """z = x + y ** power; ``power`` is a static option."""
    return {"z": inputs["x"] + inputs["y"] ** power}


def toy_passes():
    """The three toy passes a -> b -> c, in order."""
    return [
        Pass("a", make_x, (), ("x",)),
        Pass("b", scale_x, ("x",), ("y",), params={"scale": 2.0}),
        Pass("c", combine, ("x", "y"), ("z",)),
    ]


def test_order_independent_of_given_order():
    a, b, c = toy_passes()
    for shuffled in ([c, a, b], [b, c, a], [c, b, a], [a, b, c]):
        assert [p.name for p in Pipeline(shuffled).passes] == ["a", "b", "c"]


def test_order_stable_where_free():
    a, b, c = toy_passes()
    d = Pass("d", lambda p, i, s: {"w": i["x"]}, ("x",), ("w",))
    assert [p.name for p in Pipeline([d, c, a, b]).passes] == ["a", "d", "b", "c"]
    assert [p.name for p in Pipeline([c, a, b, d]).passes] == ["a", "b", "c", "d"]


def test_default_outputs_are_sinks_and_describe():
    pipe = Pipeline(toy_passes()[::-1])
    assert pipe.outputs == ("z",)
    assert pipe.buffers == ("x", "y", "z")
    text = pipe.describe()
    assert text.index("a: - -> x") < text.index("b: x -> y [params]") < text.index("c: x, y -> z")


def test_missing_input_names_consumer_and_buffer():
    a, b, c = toy_passes()
    with pytest.raises(PipelineError, match=r"pass 'c' consumes buffer 'y'.*available buffers: \['x', 'z'\]"):
        Pipeline([a, c])


def test_two_producers():
    a, b, c = toy_passes()
    a2 = Pass("a2", make_x, (), ("x",))
    with pytest.raises(PipelineError, match=r"buffer 'x' is produced by both pass 'a' and pass 'a2'"):
        Pipeline([a, b, a2])


def test_cycle_names_its_passes():
    a, _, _ = toy_passes()
    p = Pass("p", lambda *_: {"u": 0}, ("x", "v"), ("u",))
    q = Pass("q", lambda *_: {"v": 0}, ("u",), ("v",))
    r = Pass("r", lambda *_: {"t": 0}, ("v",), ("t",))  # downstream of the cycle, not part of it
    with pytest.raises(PipelineError, match=r"cycle: q -> p -> q \(through buffers \['v', 'u'\]\)$"):
        Pipeline([r, a, p, q])
    selfloop = Pass("s", lambda *_: {"k": 0}, ("k",), ("k",))
    with pytest.raises(PipelineError, match=r"cycle: s -> s \(through buffers \[.k.\]\)"):
        Pipeline([selfloop])


def test_duplicate_pass_names():
    a, b, _ = toy_passes()
    with pytest.raises(PipelineError, match=r"two passes are named 'a'"):
        Pipeline([a, b, Pass("a", lambda *_: {"w": 0}, (), ("w",))])


def test_requested_output_nobody_produces():
    with pytest.raises(PipelineError, match=r"output\(s\) \['zz'\] are produced by no pass"):
        Pipeline(toy_passes(), outputs=("zz",))
    with pytest.raises(PipelineError, match=r"\['q'\] are produced by no pass"):
        Pipeline(toy_passes()).frame("q")


def test_pass_returning_wrong_buffers_named_at_trace_time():
    a = toy_passes()[0]
    extra = Pass("bad", lambda p, i, s: {"y": i["x"], "w": i["x"]}, ("x",), ("y",))
    with pytest.raises(PipelineError, match=r"pass 'bad' .*undeclared \['w'\]"):
        Pipeline([a, extra])({}, SCENE)
    missing = Pass("bad", lambda p, i, s: {"y": i["x"]}, ("x",), ("y", "w"))
    with pytest.raises(PipelineError, match=r"pass 'bad' .*missing \['w'\]"):
        Pipeline([a, missing])({}, SCENE)


def test_pass_declaration_errors():
    with pytest.raises(PipelineError, match=r"pass 'c'.*unexpected keyword argument 'powr'"):
        Pass("c", combine, ("x", "y"), ("z",), options={"powr": 2})
    with pytest.raises(PipelineError, match=r"pass 'c': option power=\[2\] is not hashable"):
        Pass("c", combine, ("x", "y"), ("z",), options={"power": [2]})
    with pytest.raises(PipelineError, match=r"'counters' is reserved"):
        Pass("n", make_x, (), ("counters",))


def test_params_keys_are_strict():
    pipe = Pipeline(toy_passes())
    assert pipe.init_params().keys() == {"b"}
    with pytest.raises(PipelineError, match=r"missing entries for passes \['b'\]"):
        pipe({}, SCENE)
    with pytest.raises(PipelineError, match=r"unexpected entries \['bb'\]"):
        pipe({"b": {"scale": 2.0}, "bb": {"scale": 1.0}}, SCENE)


def test_intermediate_buffers_requestable():
    pipe = Pipeline(toy_passes())
    out = pipe(pipe.init_params(), SCENE, outputs=("x", "y", "z"))
    x = np.arange(4) + 1.0
    np.testing.assert_allclose(out["x"], x)
    np.testing.assert_allclose(out["y"], 2 * x)
    np.testing.assert_allclose(out["z"], 3 * x)
    assert set(out) == {"x", "y", "z", "counters"}


def test_pruning_skips_unneeded_passes():
    traced = []

    def counting(name, fn):
        def wrapped(params, inputs, scene, **options):
            traced.append(name)
            return fn(params, inputs, scene, **options)
        return wrapped

    pipe = Pipeline([Pass(p.name, counting(p.name, p.fn), p.inputs, p.outputs, params=p.params)
                     for p in toy_passes()])
    out = pipe(pipe.init_params(), SCENE, outputs="x")
    assert traced == ["a"] and set(out["counters"]) == {"a"}
    traced.clear()
    pipe(pipe.init_params(), SCENE, outputs="y")
    assert traced == ["a", "b"]
    traced.clear()
    pipe(pipe.init_params(), SCENE, outputs="y")  # cached: not traced again
    assert traced == []


def test_replace_and_with_options_change_results():
    pipe = Pipeline(toy_passes())
    params = pipe.init_params()
    x = np.arange(4) + 1.0
    powered = pipe.with_options("c", power=2)
    np.testing.assert_allclose(powered(params, SCENE)["z"], x + (2 * x) ** 2)
    np.testing.assert_allclose(pipe(params, SCENE)["z"], 3 * x)  # the original is untouched
    negated = pipe.replace("b", Pass("b", lambda p, i, s: {"y": -p["scale"] * i["x"]}, ("x",), ("y",),
                                     params={"scale": 2.0}))
    np.testing.assert_allclose(negated(params, SCENE)["z"], -x)
    assert [p.name for p in negated.passes] == ["a", "b", "c"]
    with pytest.raises(PipelineError, match=r"no pass named 'nope'"):
        pipe.with_options("nope", power=2)


def test_counters_collected():
    out = Pipeline(toy_passes())({"b": {"scale": 2.0}}, SCENE)
    assert out["counters"]["a"] == {"elements": 4}
    assert out["counters"]["b"] == {} and out["counters"]["c"] == {}


def test_jitted_equals_passes_run_in_order():
    pipe = Pipeline(toy_passes()[::-1])
    params = {"b": {"scale": jnp.float32(0.5)}}
    x = make_x(None, {}, SCENE)[0]["x"]
    y = scale_x(params["b"], {"x": x}, SCENE)["y"]
    z = combine(None, {"x": x, "y": y}, SCENE)["z"]
    np.testing.assert_allclose(pipe(params, SCENE)["z"], z, rtol=1e-6)


def test_grad_through_params_and_optax_update():
    pipe = Pipeline(toy_passes())
    frame = pipe.frame("y")

    def loss(params):
        return jnp.sum(frame(params, SCENE)["y"])

    params = pipe.init_params()
    grads = jax.grad(loss)(params)
    np.testing.assert_allclose(grads["b"]["scale"], np.sum(np.arange(4) + 1.0))
    optimizer = optax.sgd(0.1)
    updates, _ = optimizer.update(grads, optimizer.init(params))
    np.testing.assert_allclose(optax.apply_updates(params, updates)["b"]["scale"], 2.0 - 1.0)


def test_static_options_are_python_values():
    def ramp(params, inputs, scene, *, n):
        return {"r": jnp.arange(n, dtype=jnp.float32) * scene["base"][0]}

    pipe = Pipeline([Pass("ramp", ramp, (), ("r",), options={"n": 3})])
    assert pipe({}, SCENE)["r"].shape == (3,)
    assert pipe.with_options("ramp", n=5)({}, SCENE)["r"].shape == (5,)
