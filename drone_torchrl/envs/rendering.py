"""pygame drawing of one 2D drone, shared by :class:`~.drone_env.DroneEnv` and ``Drone2D-v0``.

The frame shows the domain (the env's ``x_limit``, ``z_min``, ``z_max``: 4 m x 4 m by default),
scaled to fit, with a 1 m grid and axis labels, the target zone (the env's) as a translucent rectangle, the drone as a bar of length ``motor_distance`` rotated by ``alpha`` with its
two motors, each motor's thrust as an arrow along the body's up-axis (length proportional to the
thrust fraction; a negative thrust is drawn in another colour and points down relative to the
body) and a header with the step, the return so far, the termination cause and the thrusts.

pygame is imported only when a :class:`DroneRenderer` is built, so the envs work without it
as long as nothing is drawn. ``"rgb_array"`` never opens a window (no display needed);
``"human"`` opens one (use ``SDL_VIDEODRIVER=dummy`` on a headless machine).
"""

from __future__ import annotations

import math
import os

import numpy as np

from drone_torchrl.envs.dynamics import ALPHA, DroneParams, TerminationCause, X, Z

WINDOW_TITLE = "Drone2D"

# ----------------------------------------------------------------------------- layout (pixels)
FRAME_WIDTH = FRAME_HEIGHT = 600
HEADER_HEIGHT = 56  # text overlay band above the domain
DOMAIN_TOP_GAP = 10  # room for the top z tick label below the header
MARGIN_LEFT = MARGIN_RIGHT = 50  # the left one holds the z tick labels
MARGIN_BOTTOM = 40  # x tick labels
GRID_SPACING_M = 1.0
# The area the domain is fitted into (keeping its aspect ratio, centred horizontally).
DOMAIN_WIDTH_PX = FRAME_WIDTH - MARGIN_LEFT - MARGIN_RIGHT
DOMAIN_HEIGHT_PX = FRAME_HEIGHT - HEADER_HEIGHT - DOMAIN_TOP_GAP - MARGIN_BOTTOM
DOMAIN_TOP_PX = HEADER_HEIGHT + DOMAIN_TOP_GAP
# Pixel coordinates are clipped to this many frames around the picture so a drone flung far
# away (the state is unbounded after termination) never overflows pygame's integer coordinates.
PIXEL_CLIP = 10 * max(FRAME_WIDTH, FRAME_HEIGHT)

GRID_LINE_WIDTH, BORDER_LINE_WIDTH, FLOOR_LINE_WIDTH, ZONE_EDGE_WIDTH = 1, 2, 4, 2
BODY_THICKNESS_PX, MOTOR_RADIUS_PX, HUB_RADIUS_PX = 8, 9, 5
TICK_LABEL_GAP_PX = 6

# Thrust arrows: length in metres per unit of thrust fraction (0.5 = hover -> 0.5 m), capped so an
# unbounded action stays on screen; the header shows the exact values.
THRUST_ARROW_M_PER_UNIT = 1.0
THRUST_ARROW_MAX_M = 1.5
THRUST_ARROW_MIN_PX = 1.0  # shorter arrows are not drawn
ARROW_SHAFT_WIDTH_PX = 4
ARROW_HEAD_LENGTH_PX = 14
ARROW_HEAD_HALF_WIDTH_PX = 8
ARROW_HEAD_MAX_FRACTION = 0.5  # the head takes at most this share of a short arrow

# ----------------------------------------------------------------------------- text
FONT_SIZE, TICK_FONT_SIZE = 24, 20  # pygame's bundled default font, so it works headless and offline
TEXT_LEFT_PX, TEXT_TOP_PX = 10, 8
TEXT_LINE_SPACING_PX = 24
TEXT_ITEM_GAP_PX = 28  # between the items of one header line

# ----------------------------------------------------------------------------- colours (RGB)
MARGIN_COLOUR = (232, 232, 232)
DOMAIN_COLOUR = (255, 255, 255)
HEADER_COLOUR = (245, 245, 245)
GRID_COLOUR = (210, 210, 210)
BORDER_COLOUR = (70, 70, 70)
FLOOR_COLOUR = (120, 85, 50)
ZONE_COLOUR = (60, 180, 75)
ZONE_ALPHA = 80  # of 255: the zone is a translucent fill over the domain
ZONE_EDGE_COLOUR = (40, 140, 55)
BODY_COLOUR = (40, 40, 40)
HUB_COLOUR = (110, 110, 110)
MOTOR_LEFT_COLOUR, MOTOR_RIGHT_COLOUR = (30, 90, 200), (150, 50, 180)
THRUST_POSITIVE_COLOUR, THRUST_NEGATIVE_COLOUR = (240, 150, 0), (220, 30, 30)
TEXT_COLOUR = (20, 20, 20)
TERMINATED_TEXT_COLOUR = (160, 0, 0)
TICK_TEXT_COLOUR = (90, 90, 90)


class Layout:
    """Where the world lands in a frame: the domain of ``params`` fitted into the drawing area.

    Attributes:
        pixels_per_metre: the largest scale at which the whole domain fits.
        left_px: screen x of the domain's left edge (``x = -x_limit``), centred horizontally.
    """

    def __init__(self, params: DroneParams) -> None:
        self.params = params
        self.pixels_per_metre = min(
            DOMAIN_WIDTH_PX / (2 * params.x_limit), DOMAIN_HEIGHT_PX / (params.z_max - params.z_min)
        )
        self.left_px = MARGIN_LEFT + 0.5 * (DOMAIN_WIDTH_PX - 2 * params.x_limit * self.pixels_per_metre)

    def to_pixel(self, x: float, z: float) -> tuple[float, float]:
        """Screen coordinates of the world point ``(x, z)`` (metres); the screen's y axis points down."""
        px = self.left_px + (x + self.params.x_limit) * self.pixels_per_metre
        py = DOMAIN_TOP_PX + (self.params.z_max - z) * self.pixels_per_metre
        return float(np.clip(px, -PIXEL_CLIP, PIXEL_CLIP)), float(np.clip(py, -PIXEL_CLIP, PIXEL_CLIP))


def _ticks(low: float, high: float) -> list[float]:
    """The grid lines' positions in ``[low, high]``: the multiples of :data:`GRID_SPACING_M`."""
    first, last = math.ceil(low / GRID_SPACING_M), math.floor(high / GRID_SPACING_M)
    return [k * GRID_SPACING_M for k in range(first, last + 1)]


class DroneRenderer:
    """Draws one drone with pygame.

    ``render_mode="rgb_array"``: :meth:`draw` returns an ``H x W x 3`` uint8 frame.
    ``render_mode="human"``: :meth:`draw` updates a window, keeps it responsive, waits to hold
    ``fps`` frames per second and returns ``None``.

    Args:
        render_mode: ``"human"`` or ``"rgb_array"``.
        params: the drone and its arena, which sets the drawing's scale.
        fps: the frames per second a ``"human"`` window holds.
    """

    def __init__(self, render_mode: str, params: DroneParams, fps: int) -> None:
        os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
        import pygame  # a dependency, imported only when something is drawn

        self._pygame = pygame
        self.render_mode = render_mode
        self.params = params
        self.layout = Layout(params)
        self.fps = int(fps)
        pygame.font.init()
        self._font = pygame.font.Font(None, FONT_SIZE)
        self._tick_font = pygame.font.Font(None, TICK_FONT_SIZE)
        self._canvas = pygame.Surface((FRAME_WIDTH, FRAME_HEIGHT))
        self._background = self._draw_background()
        self._window = self._clock = None
        if render_mode == "human":
            pygame.display.init()
            pygame.display.set_caption(WINDOW_TITLE)
            self._window = pygame.display.set_mode((FRAME_WIDTH, FRAME_HEIGHT))
            self._clock = pygame.time.Clock()

    # ------------------------------------------------------------------ static scene
    def _draw_background(self):
        """Margins, domain, grid, axis labels, floor and target zone: the same in every frame."""
        pygame = self._pygame
        p, to_pixel = self.params, self.layout.to_pixel
        surface = pygame.Surface((FRAME_WIDTH, FRAME_HEIGHT))
        surface.fill(MARGIN_COLOUR)
        (left, top, right, bottom), domain = self._box(p.x_limit, p.z_min, p.z_max)
        surface.fill(DOMAIN_COLOUR, domain)

        x_ticks, z_ticks = _ticks(-p.x_limit, p.x_limit), _ticks(p.z_min, p.z_max)
        for x in x_ticks:
            px, _ = to_pixel(x, p.z_min)
            pygame.draw.line(surface, GRID_COLOUR, (px, top), (px, bottom), GRID_LINE_WIDTH)
            self._tick_label(surface, f"{x:g}", (px, bottom + TICK_LABEL_GAP_PX), "midtop")
        for z in z_ticks:
            _, py = to_pixel(-p.x_limit, z)
            pygame.draw.line(surface, GRID_COLOUR, (left, py), (right, py), GRID_LINE_WIDTH)
            self._tick_label(surface, f"{z:g}", (left - TICK_LABEL_GAP_PX, py), "midright")
        # Axis titles sit between the last two tick labels of each axis.
        title_x, _ = to_pixel(x_ticks[-1] - 0.5 * GRID_SPACING_M if x_ticks else 0.0, p.z_min)
        self._tick_label(surface, "x [m]", (title_x, bottom + TICK_LABEL_GAP_PX), "midtop")
        _, title_z = to_pixel(-p.x_limit, (z_ticks[-1] if z_ticks else p.z_max) - 0.5 * GRID_SPACING_M)
        self._tick_label(surface, "z [m]", (left - TICK_LABEL_GAP_PX, title_z), "midright")

        _, zone = self._box(p.zone_x_limit, p.zone_z_min, p.zone_z_max)
        fill = pygame.Surface(zone.size, pygame.SRCALPHA)
        fill.fill((*ZONE_COLOUR, ZONE_ALPHA))
        surface.blit(fill, zone.topleft)
        pygame.draw.rect(surface, ZONE_EDGE_COLOUR, zone, ZONE_EDGE_WIDTH)

        pygame.draw.rect(surface, BORDER_COLOUR, domain, BORDER_LINE_WIDTH)
        pygame.draw.line(surface, FLOOR_COLOUR, (left, bottom), (right, bottom), FLOOR_LINE_WIDTH)
        return surface

    def _box(self, x_limit: float, z_low: float, z_high: float):
        """The world box ``|x| <= x_limit``, ``z_low <= z <= z_high`` on screen: its edges and its Rect."""
        left, top = self.layout.to_pixel(-x_limit, z_high)
        right, bottom = self.layout.to_pixel(x_limit, z_low)
        rect = self._pygame.Rect(round(left), round(top), round(right - left), round(bottom - top))
        return (left, top, right, bottom), rect

    def _tick_label(self, surface, text: str, position: tuple[float, float], anchor: str) -> None:
        """A grid or axis label whose ``anchor`` point (``"midtop"``, ...) lies on ``position``."""
        image = self._tick_font.render(text, True, TICK_TEXT_COLOUR)
        surface.blit(image, image.get_rect(**{anchor: (round(position[0]), round(position[1]))}))

    # ------------------------------------------------------------------ drone
    def _draw_arrow(self, start: np.ndarray, direction: np.ndarray, length_px: float, colour) -> None:
        """An arrow of ``length_px`` pixels from ``start`` along the unit screen vector ``direction``."""
        if length_px < THRUST_ARROW_MIN_PX:
            return
        pygame = self._pygame
        head = min(ARROW_HEAD_LENGTH_PX, ARROW_HEAD_MAX_FRACTION * length_px)
        half_width = ARROW_HEAD_HALF_WIDTH_PX * head / ARROW_HEAD_LENGTH_PX
        normal = np.array([-direction[1], direction[0]])
        tip = start + direction * length_px
        base = tip - direction * head
        pygame.draw.line(self._canvas, colour, tuple(start), tuple(base), ARROW_SHAFT_WIDTH_PX)
        pygame.draw.polygon(
            self._canvas,
            colour,
            [tuple(tip), tuple(base + normal * half_width), tuple(base - normal * half_width)],
        )

    def _draw_drone(self, state: np.ndarray, action: np.ndarray) -> None:
        pygame = self._pygame
        x, z, alpha = float(state[X]), float(state[Z]), float(state[ALPHA])
        # Body axes (alpha CCW from vertical): "right" points from the centre to the right motor, "up"
        # is the thrust direction (eq. 2.1: x_ddot ~ sin(-alpha)); in the screen frame, whose y points
        # down, their world z components flip sign.
        right_s = np.array([math.cos(alpha), -math.sin(alpha)])
        up_s = np.array([-math.sin(alpha), -math.cos(alpha)])
        centre = np.array(self.layout.to_pixel(x, z))
        pixels_per_metre = self.layout.pixels_per_metre
        half_length = self.params.lever_arm * pixels_per_metre
        motors = (centre - right_s * half_length, centre + right_s * half_length)

        for motor, thrust in zip(motors, action, strict=True):
            thrust = float(thrust)
            colour = THRUST_NEGATIVE_COLOUR if thrust < 0 else THRUST_POSITIVE_COLOUR
            length_m = min(abs(thrust) * THRUST_ARROW_M_PER_UNIT, THRUST_ARROW_MAX_M)
            direction = up_s if thrust >= 0 else -up_s
            self._draw_arrow(motor, direction, length_m * pixels_per_metre, colour)

        normal = up_s * (0.5 * BODY_THICKNESS_PX)
        left_motor, right_motor = motors
        corners = [left_motor + normal, right_motor + normal, right_motor - normal, left_motor - normal]
        pygame.draw.polygon(self._canvas, BODY_COLOUR, [tuple(c) for c in corners])
        pygame.draw.circle(self._canvas, HUB_COLOUR, tuple(centre), HUB_RADIUS_PX)
        pygame.draw.circle(self._canvas, MOTOR_LEFT_COLOUR, tuple(left_motor), MOTOR_RADIUS_PX)
        pygame.draw.circle(self._canvas, MOTOR_RIGHT_COLOUR, tuple(right_motor), MOTOR_RADIUS_PX)

    def _draw_overlay(self, state, action, step: int, episode_return: float, cause: TerminationCause) -> None:
        """Header text: step, return and cause on the first line, thrusts and tilt on the second."""
        self._canvas.fill(HEADER_COLOUR, (0, 0, FRAME_WIDTH, HEADER_HEIGHT))
        ink, alarm = TEXT_COLOUR, TEXT_COLOUR if cause == TerminationCause.NONE else TERMINATED_TEXT_COLOUR
        a_l, a_r = (float(a) for a in action)
        alpha_deg = math.degrees(float(state[ALPHA]))
        lines = (
            [(f"step {step}", ink), (f"return {episode_return:.1f}", ink), (f"cause {cause.name}", alarm)],
            [(f"thrust L {a_l:+.2f}  R {a_r:+.2f} (x weight)", ink), (f"alpha {alpha_deg:+.1f} deg", ink)],
        )
        for row, items in enumerate(lines):
            left, top = TEXT_LEFT_PX, TEXT_TOP_PX + row * TEXT_LINE_SPACING_PX
            for text, colour in items:
                image = self._font.render(text, True, colour)
                self._canvas.blit(image, (left, top))
                left += image.get_width() + TEXT_ITEM_GAP_PX

    # ------------------------------------------------------------------ public API
    def draw(
        self,
        state: np.ndarray,
        action: np.ndarray,
        step: int,
        episode_return: float,
        cause: TerminationCause,
    ) -> np.ndarray | None:
        """Draw one frame; returns it as ``H x W x 3`` uint8 in ``"rgb_array"`` mode, else ``None``."""
        pygame = self._pygame
        state = np.asarray(state, dtype=np.float64).reshape(-1)
        action = np.asarray(action, dtype=np.float64).reshape(-1)
        self._canvas.blit(self._background, (0, 0))
        # The drone may leave the domain (into the margins) but never covers the header.
        self._canvas.set_clip(pygame.Rect(0, HEADER_HEIGHT, FRAME_WIDTH, FRAME_HEIGHT - HEADER_HEIGHT))
        if np.isfinite(state).all() and np.isfinite(action).all():
            self._draw_drone(state, action)
        self._canvas.set_clip(None)
        self._draw_overlay(state, action, step, episode_return, cause)

        if self.render_mode == "human":
            pygame.event.pump()
            self._window.blit(self._canvas, (0, 0))
            pygame.display.flip()
            self._clock.tick(self.fps)
            return None
        # Row-major RGB bytes (writable): a quarter of the time of surfarray's column-major copy
        # transposed and copied again.
        pixels = bytearray(pygame.image.tobytes(self._canvas, "RGB"))
        return np.frombuffer(pixels, dtype=np.uint8).reshape(FRAME_HEIGHT, FRAME_WIDTH, 3)

    def close(self) -> None:
        """Close the window (``"human"`` mode); safe to call more than once."""
        if self._window is not None:
            self._pygame.display.quit()
            self._window = self._clock = None
