import numpy as np
import pytest
from scipy.special import expit, softmax

from calibrators.scores import class_probabilities, predict


def test_sigmoid_probabilities_and_labels():
    z = np.array([[0.0, 2.0, -1.0], [3.0, -2.0, 1.0]])
    p = class_probabilities(z, "sigmoid", temperature=2.0)
    np.testing.assert_allclose(p, expit(z / 2.0))
    labels, scores = predict(z, "sigmoid", temperature=2.0)
    assert labels.tolist() == [1, 0]
    np.testing.assert_allclose(scores, expit(np.array([2.0, 3.0]) / 2.0))


def test_softmax_drops_no_object_column_and_label_ignores_it():
    z = np.array([[1.0, 0.5, 9.0]])  # no-object column is the largest
    p = class_probabilities(z, "softmax")
    np.testing.assert_allclose(p, softmax(z, axis=1)[:, :2])
    labels, scores = predict(z, "softmax")
    assert labels.tolist() == [0]
    assert scores[0] == pytest.approx(softmax(z, axis=1)[0, 0])


@pytest.mark.parametrize("mode", ["sigmoid", "softmax"])
def test_temperature_never_changes_argmax(mode):
    rng = np.random.default_rng(0)
    z = rng.normal(0, 3, size=(500, 6)).astype(np.float32)
    base = predict(z, mode)[0]
    for t in (0.1, 0.7, 3.0, 50.0):
        assert np.array_equal(predict(z, mode, temperature=t)[0], base)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"logits": [[np.nan, 1.0]], "mode": "sigmoid"}, "logits has NaN at index \\[0, 0\\]"),
        ({"logits": [1.0, 2.0], "mode": "sigmoid"}, "logits must have 2 dimensions"),
        ({"logits": [[1.0]], "mode": "softmax"}, "at least 2 columns"),
        ({"logits": [[1.0]], "mode": "tanh"}, "score_mode must be one of"),
        ({"logits": [[1.0]], "mode": "sigmoid", "temperature": 0.0}, "temperature must be"),
    ],
)
def test_bad_input_names_the_argument(kwargs, message):
    with pytest.raises(ValueError, match=message):
        class_probabilities(**kwargs)
