"""Captions of overview.png: long ones wrap inside their panel instead of running into the next."""

from PIL import Image, ImageDraw, ImageFont

from cell.report import OVERVIEW_PANEL_PX, wrapped_caption


def test_a_long_caption_wraps_within_the_panel_and_keeps_every_word():
    draw = ImageDraw.Draw(Image.new("RGB", (10, 10)))
    font = ImageFont.load_default()
    caption = "simulated result (built upside down, shown turned back)"
    width = 0.4 * OVERVIEW_PANEL_PX
    assert draw.textlength(caption, font=font) > width  # the case at hand: one line would not fit
    lines = wrapped_caption(caption, lambda text: draw.textlength(text, font=font), width).split("\n")
    assert len(lines) > 1
    assert all(draw.textlength(line, font=font) <= width for line in lines)
    assert " ".join(lines) == caption


def test_a_short_caption_stays_one_line_and_a_too_long_word_gets_its_own():
    def width_px(text):
        return 10 * len(text)

    assert wrapped_caption("input image", width_px, 200) == "input image"
    assert wrapped_caption("a averyveryverylongword b", width_px, 50) == "a\naveryveryverylongword\nb"
