// The on-screen joystick: pointer events, so a finger, a pen and a mouse drive it alike.
//
// The element holds a knob; pressing anywhere on it grabs the knob (pointer capture:
// the drag goes on outside it), and letting go, a cancelled touch or a lost capture
// puts the knob back in the middle and tells `onRelease`. `onMove(x, y)` gets the
// knob's position within the unit circle, x to the right, y up.

const DEAD_ZONE = 0.08;

export class Joystick {
  constructor(element, knob, { onMove, onRelease }) {
    this.element = element;
    this.knob = knob;
    this.onMove = onMove;
    this.onRelease = onRelease;
    this.pointer = null;
    this.enabled = false;
    element.addEventListener("pointerdown", (event) => this.down(event));
    element.addEventListener("pointermove", (event) => this.move(event));
    for (const type of ["pointerup", "pointercancel", "lostpointercapture"]) {
      element.addEventListener(type, (event) => {
        if (event.pointerId === this.pointer) this.release();
      });
    }
  }

  get held() {
    return this.pointer !== null;
  }

  setEnabled(enabled) {
    this.enabled = enabled;
    this.element.setAttribute("aria-disabled", String(!enabled));
    if (!enabled) this.release();
  }

  down(event) {
    if (!this.enabled || this.pointer !== null) return;
    event.preventDefault();
    this.pointer = event.pointerId;
    this.element.setPointerCapture(event.pointerId);
    this.element.classList.add("held");
    this.move(event);
  }

  move(event) {
    if (event.pointerId !== this.pointer) return;
    const box = this.element.getBoundingClientRect();
    const radius = box.width / 2;
    let x = (event.clientX - (box.left + radius)) / radius;
    let y = -(event.clientY - (box.top + box.height / 2)) / radius;
    const length = Math.hypot(x, y);
    if (length > 1) {
      x /= length;
      y /= length;
    }
    this.place(x, y);
    const live = Math.hypot(x, y) < DEAD_ZONE ? [0, 0] : [x, y];
    this.onMove(live[0], live[1]);
  }

  place(x, y) {
    // The knob's centre travels to the base's rim, less its own radius.
    const travel = (this.element.clientWidth - this.knob.offsetWidth) / 2;
    this.knob.style.transform = `translate(${x * travel}px, ${-y * travel}px)`;
  }

  /** Let go: the knob goes back to the middle, and `onRelease` is told (once). */
  release() {
    if (this.pointer === null) return;
    const pointer = this.pointer;
    this.pointer = null;
    if (this.element.hasPointerCapture(pointer)) this.element.releasePointerCapture(pointer);
    this.element.classList.remove("held");
    this.place(0, 0);
    this.onRelease();
  }
}
