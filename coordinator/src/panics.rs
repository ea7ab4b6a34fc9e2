//! Panics anywhere in the coordinator fail the render: a hook records the
//! first, and the farm's supervisor ([`crate::farm::Farm::tick`]) ends the
//! render (or the service) with it, for a non-zero exit. Without it a panic
//! in a spawned task (a gRPC handler, a preview writer) would end only that
//! task, and the render would go on, or wait, on a state nobody can trust.

use std::sync::OnceLock;

/// The first panic recorded.
static FIRST: OnceLock<String> = OnceLock::new();

/// Installs the hook (once per process; the previous hook still runs, so
/// the panic is printed as usual).
pub fn install() {
    static INSTALLED: std::sync::Once = std::sync::Once::new();
    INSTALLED.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            let thread = std::thread::current();
            if counts(thread.name()) {
                let _ = FIRST.set(format!(
                    "panic on thread {}: {info}",
                    thread.name().unwrap_or("?")
                ));
            }
            previous(info);
        }));
    });
}

/// Whether a panic on the thread named `name` is the coordinator's. A
/// render thread's is not: a worker (the in-process ones included) catches
/// it and reports the unit as failed, which the scheduler handles.
fn counts(name: Option<&str>) -> bool {
    !name.is_some_and(|n| n.starts_with("render-"))
}

/// The first panic recorded since [`install`], if any.
pub fn first() -> Option<&'static str> {
    FIRST.get().map(String::as_str)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_in_a_spawned_task_is_recorded_and_a_render_threads_is_not() {
        install();
        let render = std::thread::Builder::new()
            .name("render-0".into())
            .spawn(|| panic!("a unit's render"))
            .unwrap()
            .join();
        assert!(render.is_err());
        assert_eq!(first(), None, "a render thread's panic is a unit failure");
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        let task = runtime.block_on(async { tokio::spawn(async { panic!("in a handler") }).await });
        assert!(task.is_err());
        let recorded = first().expect("recorded");
        assert!(recorded.contains("in a handler"), "{recorded}");
    }
}
