"""Judging a candidate pair: the quality gate, local features, matching and the geometric check."""

from .features import FEATURES, SIFT, FeatureExtractor, Features, create_extractor
from .gate import EdgeGate, GateResult
from .geometry import GeometricVerifier, GeometryResult
from .matching import match_ratio, match_ratio_many
from .verifier import MATCHERS, RatioTestMatcher, Verification, Verifier, create_verifier, scale_change

__all__ = ["EdgeGate", "GateResult", "Features", "FeatureExtractor", "SIFT", "FEATURES", "create_extractor",
           "GeometricVerifier", "GeometryResult", "match_ratio", "match_ratio_many", "Verification", "Verifier",
           "RatioTestMatcher", "MATCHERS", "create_verifier", "scale_change"]
