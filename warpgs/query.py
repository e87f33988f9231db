"""Open-vocabulary queries on language fields: see `warpgs.language.query` (this module re-exports it)."""
from warpgs.language.query import LanguageField, QueryResult, normalise_relevancy, relevancy_scores  # noqa: F401

__all__ = ["LanguageField", "QueryResult", "normalise_relevancy", "relevancy_scores"]
