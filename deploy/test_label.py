"""Unit tests of deploy/label.py's summary of an attempt (run by tests/labelling.rs):
    python3 -m unittest deploy/test_label.py"""

import os
import sys
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import label  # noqa: E402


def attempt():
    # 6 frames: frame 0 after reset, a lead-in of 2 steps (segment_from 2), then 3 judged
    # steps (frames 3-5). One particle is eaten in the lead-in, two in the judged part.
    return {
        "segment_from": 2,
        "readout": {
            "distance": [0.30, 0.20, 0.02, 0.10, 0.04, 0.12],
            "speed": [0.0, 0.5, 0.4, 0.1, 0.2, 0.3],
            "force": [0.0, 0.0, 3.0, 0.0, 1.5, 0.0],
            "food": [[8, 0, 0, 0], [8, 0, 0, 0], [7, 1, 0, 0], [6, 2, 0, 0],
                     [4, 3, 1, 1], [3, 3, 1, 1]],
        },
    }


class Summary(unittest.TestCase):
    def test_numbers_are_over_the_judged_part_only(self):
        s = label.summarise(attempt())
        # The lead-in's 2 cm (frame 2) and its 3 N are not judged.
        self.assertAlmostEqual(s["closest"], 0.04)
        self.assertAlmostEqual(s["mean_distance"], (0.10 + 0.04 + 0.12) / 3)
        self.assertAlmostEqual(s["top_speed"], 0.3)
        self.assertAlmostEqual(s["mean_speed"], 0.2)
        self.assertAlmostEqual(s["peak_force"], 1.5)
        self.assertEqual((s["eaten"], s["spilled"], s["hits"], s["left"]), (2, 1, 1, 3))

    def test_the_description_prints_the_food_eaten(self):
        pair = {"steps": 5, "left": attempt(), "right": attempt()}
        text = label.describe(pair)
        self.assertEqual(text.count("food eaten 2, spilled 1, on the person 1"), 2, text)
        self.assertIn("closest 4.0 cm", text)

    def test_an_attempt_without_a_readout_is_said_so(self):
        with self.assertRaises(ValueError):
            label.summarise({"frames": {"spoon": [[0, 0, 0]]}})
        self.assertIn("no readout", label.describe({"left": {}, "right": attempt()}))


class Ranking(unittest.TestCase):
    def test_a_ranking_typed_best_to_worst_gives_each_attempt_its_place(self):
        self.assertEqual(label.places_of("2 3 1", 3), [2, 0, 1])
        self.assertEqual(label.places_of("2=3 1", 3), [2, 0, 0])
        self.assertEqual(label.places_of("4 1=2 3", 4), [1, 1, 3, 0])
        for bad in ("2 2 1", "1 2", "1 2 4", "a b c", ""):
            self.assertIsNone(label.places_of(bad, 3), bad)

    def test_a_ranking_is_described_attempt_by_attempt(self):
        text = label.describe({"kind": "rank", "attempts": [attempt(), attempt(), attempt()]})
        for k in ("1:", "2:", "3:"):
            self.assertIn(k, text)


if __name__ == "__main__":
    unittest.main()
