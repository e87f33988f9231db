"""What few-view switches with an "auto" setting (train.virtual_views, train.drop_rate) share: their rule counts the
run's training views, and the start line says when "auto" left one off."""
from __future__ import annotations


def auto_off_note(what: str, key: str, num_train_views: int, most: int) -> str:
    """The start line's words for a switch that "auto" left off with this many training views."""
    return f"; {what} off (train.{key}=auto: {num_train_views} training views, on with at most {most})"
