"""The offscreen 3D view's frames, drawn on a thread of their own so that a slow frame never freezes the window.

Without a GPU (Mesa llvmpipe) one frame of a 512k-face mesh takes 0.2–2 s; drawn on the GUI thread it froze
the window that long (issue 5). Here the GUI thread keeps the pyvista plotter as the scene's model (tools
add and remove actors, pick, move the camera; it is never rendered) and hands a snapshot of it to a render
thread, which draws the latest snapshot in its own offscreen window and sends the picture back.

A snapshot copies only what the GUI thread may change while a frame is being drawn: the camera, the
lights, each actor's property, mapper settings and dataset object (sharing the arrays, which are replaced,
not edited, when a scene changes; datasets are given to mappers as data, as pyvista does, not as the
output of a pipeline the GUI thread would have to run). The copies are cached by VTK modification time, so an unchanged actor
keeps its copy and the render thread its uploaded buffers: a camera move does not upload the mesh again.
All OpenGL resources live and die on the render thread (copies are released there before they are dropped).
Every other prop (a scalar bar, a text) is copied too, with its own lookup table and text and 2D properties:
shared, the GUI thread changed a scalar bar's lookup table while the render thread drew it, and removing it
released its OpenGL resources on the GUI thread (VTK releases a removed prop's resources for the viewport
it leaves), under the render thread's feet: a crash now and then (issue 5).
"""

from __future__ import annotations

import atexit
import os
import threading
from dataclasses import dataclass, field

import numpy as np
from PySide6.QtCore import QObject, Signal
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkRenderingCore import (vtkActor, vtkCamera, vtkLight, vtkProperty, vtkRenderer, vtkRenderWindow,
                                         vtkTexture, vtkWindowToImageFilter)

from engine.render import max_texture_size

RENDERER_SETTINGS = ("Background", "Background2", "GradientBackground", "TwoSidedLighting", "LightFollowCamera",
                     "AutomaticLightCreation", "UseFXAA", "UseDepthPeeling", "MaximumNumberOfPeels",
                     "OcclusionRatio")
TEXTURE_SETTINGS = ("Interpolate", "Mipmap", "Repeat", "EdgeClamp", "ColorMode", "UseSRGBColorSpace",
                    "MaximumAnisotropicFiltering", "PremultipliedAlpha", "BlendingMode", "CubeMap", "Quality",
                    "RestrictPowerOf2ImageSmaller", "LookupTable", "Transform")
RENDER_NICENESS = 5  # added to the render thread's niceness (Linux): frames yield the cores to the GUI thread
SYNC_TIMEOUT = 120.0  # s a blocking `frame()` waits at most (a frame takes seconds on a busy machine)
# the parts of a 2D prop (vtkScalarBarActor, vtkTextActor, vtkCornerAnnotation, vtkActor2D) that its
# ShallowCopy shares and the GUI thread may change: each copy gets its own
PROP_PARTS = ("LookupTable", "Property", "TextProperty", "TitleTextProperty", "LabelTextProperty",
              "AnnotationTextProperty", "FrameProperty", "BackgroundProperty")

_LIVE: set[RenderThread] = set()  # threads not yet ended (stopped or not), stopped and waited for at exit


@dataclass
class _Snapshot:
    """What the render thread draws: all copies, none of them touched again by the GUI thread."""

    number: int
    size: tuple[int, int]
    samples: int
    settings: dict
    camera: vtkCamera
    lights: list[vtkLight]
    props: list[tuple[object, vtkActor | None]]  # (prop to draw, latest state of a mirror actor or None: a
    # copied 2D prop is drawn as it is)


class _Signals(QObject):
    drawn = Signal(object)  # (H, W, 3) uint8, in the GUI thread
    failed = Signal(object)  # the exception


@dataclass
class _Mirror:
    """The render thread's copy of one GUI actor, the GUI actor's latest state and when it was taken."""

    source: vtkActor
    actor: vtkActor = field(default_factory=vtkActor)
    state: vtkActor | None = None
    key: tuple = ()


class RenderThread:
    """Draws snapshots of `plotter`'s scene on a thread of its own; `signals.drawn` delivers each picture.

    `request()` (cheap, GUI thread) asks for a frame of the scene as it is now: the thread draws the latest
    request when it is free, so a burst of requests (a drag) costs one frame per frame time. `frame()`
    draws now and waits for the picture (a screenshot, a test).
    """

    def __init__(self, plotter) -> None:
        self._plotter = plotter
        self.signals = _Signals()
        # by id(): pyvista's objects compare by value and do not hash; each entry holds its GUI object
        self._mirrors: dict[int, _Mirror] = {}  # id(GUI actor) → its mirror
        self._copies: dict[int, tuple] = {}  # id(GUI mapper or texture) → (source, modification key, copy)
        self._props: dict[int, tuple] = {}  # id(GUI 2D prop) → (source, modification key, copy)
        self._lights: tuple[tuple, list[vtkLight]] = ((), [])
        self._wake = threading.Condition()
        self._pending: _Snapshot | None = None
        self._number = 0
        self._drawn: tuple[int, np.ndarray | None, BaseException | None] = (0, None, None)
        self._stopping = False
        self.max_texture_size: int | None = None  # of the render thread's OpenGL context, once it drew a frame
        self._thread = threading.Thread(target=self._run, name="tracemap-render", daemon=True)
        self._thread.start()
        _LIVE.add(self)

    # -- GUI thread -----------------------------------------------------------------------------------

    def request(self, interactive: bool = False) -> int:
        """Ask for a frame of the scene as it is now; returns its number. An `interactive` frame (while the
        camera is being dragged) leaves out the multisampling: 4× faster without a GPU, a still follows."""
        snapshot = self._snapshot(interactive)
        with self._wake:
            self._pending = snapshot
            self._wake.notify_all()
        return snapshot.number

    def frame(self) -> np.ndarray:
        """Draw the scene as it is now and return the picture, (H, W, 3) uint8 (blocks until drawn)."""
        number = self.request()
        with self._wake:
            if not self._wake.wait_for(lambda: self._drawn[0] >= number or self._stopping, SYNC_TIMEOUT):
                raise TimeoutError(f"the 3D view did not draw a frame in {SYNC_TIMEOUT:.0f} s")
            _, image, error = self._drawn
        if error is not None:
            raise error
        if image is None:
            raise RuntimeError("the 3D view is closed")
        return image

    def stop(self, wait: bool = False) -> None:
        """End the thread after the frame it draws (its OpenGL resources are released there). Without
        `wait` it stays listed until it has ended, so that the interpreter's exit still waits for it: a
        thread drawing or releasing while Qt and the OpenGL driver are torn down crashes the process."""
        with self._wake:
            self._stopping = True
            self._wake.notify_all()
        if wait:
            self._thread.join(SYNC_TIMEOUT)

    def _snapshot(self, interactive: bool) -> _Snapshot:
        window, renderer = self._plotter.render_window, self._plotter.renderer
        self._number += 1
        camera = vtkCamera()
        camera.DeepCopy(renderer.GetActiveCamera())
        props = [self._mirror(prop) if isinstance(prop, vtkActor) and prop.GetMapper() is not None
                 else (self._copy(prop, _prop_key(prop), _copy_prop, self._props), None)
                 for prop in renderer.GetViewProps()]
        shown = {id(prop) for prop in renderer.GetViewProps()}
        self._mirrors = {key: mirror for key, mirror in self._mirrors.items() if key in shown}
        self._props = {key: copy for key, copy in self._props.items() if key in shown}
        used = {id(obj) for mirror in self._mirrors.values()
                for obj in (mirror.source.GetMapper(), mirror.source.GetTexture())}
        self._copies = {key: copy for key, copy in self._copies.items() if key in used}
        return _Snapshot(self._number, tuple(window.GetSize()), 0 if interactive else window.GetMultiSamples(),
                         {name: getattr(renderer, f"Get{name}")() for name in RENDERER_SETTINGS},
                         camera, self._copied_lights(renderer), props)

    def _mirror(self, actor: vtkActor) -> tuple[vtkActor, vtkActor]:
        """The mirror of a GUI actor and the actor's latest state, copied again only after it changed."""
        mapper, texture = actor.GetMapper(), actor.GetTexture()
        data = mapper.GetInputDataObject(0, 0)
        key = (actor.GetMTime(), actor.GetProperty().GetMTime(), mapper.GetMTime(),
               None if data is None else data.GetMTime(), None if texture is None else texture.GetMTime())
        mirror = self._mirrors.setdefault(id(actor), _Mirror(actor))
        if mirror.key != key:
            state = vtkActor()
            state.ShallowCopy(actor)
            properties = vtkProperty()
            properties.DeepCopy(actor.GetProperty())
            state.SetProperty(properties)
            state.SetMapper(self._copy(mapper, key[2:4], _copy_mapper))
            state.SetTexture(None if texture is None else self._copy(texture, key[4], _copy_texture))
            mirror.state, mirror.key = state, key
        return mirror.actor, mirror.state

    def _copy(self, source, key, make, cache: dict | None = None):
        """A copy of a GUI mapper, texture (or 2D prop, in `cache`), made again only after the source changed.
        A copy dropped here may still be in the render thread's scene, which holds it until it is released."""
        cache = self._copies if cache is None else cache
        cached = cache.get(id(source))
        if cached is None or cached[1] != key:
            cached = cache[id(source)] = (source, key, make(source))
        return cached[2]

    def _copied_lights(self, renderer) -> list[vtkLight]:
        lights = list(renderer.GetLights())
        key = tuple((id(light), light.GetMTime()) for light in lights)
        if key != self._lights[0]:
            copies = []
            for light in lights:
                copy = vtkLight()
                copy.DeepCopy(light)
                copies.append(copy)
            self._lights = (key, copies)
        return self._lights[1]

    # -- render thread --------------------------------------------------------------------------------

    def _run(self) -> None:
        if hasattr(os, "setpriority"):  # the GUI thread first: Mesa's raster threads, started below, inherit it
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), RENDER_NICENESS)
        scene = _Scene()
        while True:
            with self._wake:
                self._wake.wait_for(lambda: self._pending is not None or self._stopping)
                if self._stopping:
                    break
                snapshot, self._pending = self._pending, None
            try:
                image, error = scene.draw(snapshot), None
                self.max_texture_size = self.max_texture_size or max_texture_size(scene.window)
            except Exception as exc:  # noqa: BLE001 - reported to the GUI thread, which shows it
                image, error = None, exc
            with self._wake:
                self._drawn = (snapshot.number, image, error)
                self._wake.notify_all()
            if error is None:
                self.signals.drawn.emit(image)
            else:
                self.signals.failed.emit(error)
        scene.close()
        _LIVE.discard(self)


class _Scene:
    """The render thread's window and renderer, holding the mirrors; used on the render thread only."""

    def __init__(self) -> None:
        self.window, self.renderer = vtkRenderWindow(), vtkRenderer()
        self.window.SetOffScreenRendering(True)
        self.window.AddRenderer(self.renderer)
        self._applied: dict[int, vtkActor] = {}  # id(mirror) → the state it was last given
        self._lights: list[vtkLight] | None = None

    def draw(self, snapshot: _Snapshot) -> np.ndarray:
        """Put the snapshot into the scene, draw it and read the picture back."""
        self._update_props(snapshot.props)
        for name, value in snapshot.settings.items():
            getattr(self.renderer, f"Set{name}")(value)
        if snapshot.lights is not self._lights:
            self.renderer.RemoveAllLights()
            for light in snapshot.lights:
                self.renderer.AddLight(light)
            self._lights = snapshot.lights
        self.renderer.SetActiveCamera(snapshot.camera)
        self.window.SetMultiSamples(snapshot.samples)
        self.window.SetSize(*snapshot.size)
        self.window.Render()
        grab = vtkWindowToImageFilter()
        grab.SetInput(self.window)
        grab.SetInputBufferTypeToRGB()
        grab.ReadFrontBufferOff()
        grab.ShouldRerenderOff()
        grab.Update()
        width, height = snapshot.size
        pixels = vtk_to_numpy(grab.GetOutput().GetPointData().GetScalars()).reshape(height, width, 3)
        return np.ascontiguousarray(pixels[::-1])  # VTK's rows start at the bottom

    def _update_props(self, props: list[tuple[object, vtkActor | None]]) -> None:
        wanted = [prop for prop, _ in props]
        keep = {id(prop) for prop in wanted}
        for gone in self.renderer.GetViewProps():
            if id(gone) not in keep:
                gone.ReleaseGraphicsResources(self.window)  # here, where its buffers live
                self._applied.pop(id(gone), None)
        for mirror, state in props:
            if state is None or self._applied.get(id(mirror)) is state:
                continue
            if mirror.GetMapper() is not state.GetMapper() or mirror.GetTexture() is not state.GetTexture():
                mirror.ReleaseGraphicsResources(self.window)  # before the old mapper or texture is dropped
            mirror.ShallowCopy(state)
            self._applied[id(mirror)] = state
        collection = self.renderer.GetViewProps()
        collection.RemoveAllItems()
        for prop in wanted:  # in the GUI's order: overlays and translucent props are drawn in that order
            collection.AddItem(prop)

    def close(self) -> None:
        for prop in list(self.renderer.GetViewProps()):
            prop.ReleaseGraphicsResources(self.window)
        self.renderer.RemoveAllViewProps()
        self.window.Finalize()


def _copy_mapper(mapper):
    """A mapper with the GUI mapper's settings, its own lookup table, and its own dataset object on the
    same arrays: the render thread's pipeline and buffers never touch the GUI's."""
    copy = mapper.NewInstance()
    copy.ShallowCopy(mapper)
    data = mapper.GetInputDataObject(0, 0)
    if data is not None:
        dataset = data.NewInstance()
        dataset.ShallowCopy(data)
        copy.SetInputDataObject(dataset)
    table = mapper.GetLookupTable()
    if table is not None:
        own = table.NewInstance()
        own.DeepCopy(table)
        copy.SetLookupTable(own)
    return copy


def _prop_key(prop) -> tuple:
    """When a 2D prop or one of its parts last changed."""
    return (prop.GetMTime(), *(part.GetMTime() for part in _parts(prop).values()))


def _parts(prop) -> dict[str, object]:
    """The PROP_PARTS that `prop` has, by name."""
    parts = {name: getattr(prop, f"Get{name}")() for name in PROP_PARTS
             if hasattr(prop, f"Get{name}") and hasattr(prop, f"Set{name}")}
    return {name: part for name, part in parts.items() if part is not None}


def _copy_prop(prop):
    """A 2D prop with the GUI prop's settings and its own lookup table and properties (text, 2D)."""
    copy = prop.NewInstance()
    copy.ShallowCopy(prop)
    for name, part in _parts(prop).items():
        if getattr(copy, f"Get{name}")() is part:  # shared by ShallowCopy
            own = part.NewInstance()
            (own.DeepCopy if hasattr(own, "DeepCopy") else own.ShallowCopy)(part)  # text properties: values only
            getattr(copy, f"Set{name}")(own)
    return copy


def _copy_texture(texture: vtkTexture) -> vtkTexture:
    """A texture on the same image (uploaded once per copy, on the render thread)."""
    copy = vtkTexture()
    for name in TEXTURE_SETTINGS:
        getattr(copy, f"Set{name}")(getattr(texture, f"Get{name}")())
    image = texture.GetInputDataObject(0, 0)
    if image is not None:
        own = image.NewInstance()
        own.ShallowCopy(image)
        copy.SetInputDataObject(own)
    return copy


@atexit.register
def _stop_all() -> None:
    """Let every render thread, stopped or not, release its OpenGL resources before the interpreter goes
    (registered after PySide6's own exit handler, so it runs before Qt is torn down)."""
    for thread in list(_LIVE):
        thread.stop(wait=True)
