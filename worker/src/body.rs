//! Request bodies that say they are finished as soon as they are.
//!
//! A unary gRPC request body is one message, but it only learns that it has
//! ended when it is polled once more, so hyper sends the message in one
//! HTTP/2 DATA frame and the end of the stream in a second, empty one: one
//! more write here and one more wake-up of the coordinator, per tile.
//! [`EndStreamEarly`] wraps each request body in a [`Lookahead`] that polls
//! the inner body once more after every frame, so the last data frame goes out
//! with END_STREAM set. Nothing else changes: the same frames, in the same order.

use std::pin::Pin;
use std::task::{Context, Poll};

use http_body::{Body, Frame, SizeHint};
use tonic::codegen::{Service, http};

/// What polling a body gives when it is ready.
type Polled<B> = Option<Result<Frame<<B as Body>::Data>, <B as Body>::Error>>;

/// A body that polls its inner body one frame ahead, so that
/// [`Body::is_end_stream`] turns true together with the last frame.
pub struct Lookahead<B: Body> {
    inner: Pin<Box<B>>,
    /// The frame (or error) polled ahead, not yet handed out.
    ahead: Option<Result<Frame<B::Data>, B::Error>>,
    /// The inner body has ended.
    ended: bool,
}

// The inner body is pinned in its box; the frame held ahead is never pinned.
impl<B: Body> Unpin for Lookahead<B> {}

impl<B: Body> Lookahead<B> {
    /// Wraps `inner`.
    pub fn new(inner: B) -> Self {
        Lookahead {
            inner: Box::pin(inner),
            ahead: None,
            ended: false,
        }
    }

    fn poll_inner(&mut self, cx: &mut Context<'_>) -> Poll<Polled<B>> {
        if self.ended {
            return Poll::Ready(None);
        }
        let polled = self.inner.as_mut().poll_frame(cx);
        if let Poll::Ready(None) = polled {
            self.ended = true;
        }
        polled
    }
}

impl<B: Body> Body for Lookahead<B> {
    type Data = B::Data;
    type Error = B::Error;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Self::Data>, Self::Error>>> {
        let this = self.get_mut();
        let frame = match this.ahead.take() {
            Some(frame) => frame,
            None => match this.poll_inner(cx) {
                Poll::Ready(Some(frame)) => frame,
                other => return other,
            },
        };
        if frame.is_ok() {
            // Look one frame ahead; Pending leaves the end unknown, as before.
            if let Poll::Ready(Some(next)) = this.poll_inner(cx) {
                this.ahead = Some(next);
            }
        }
        Poll::Ready(Some(frame))
    }

    fn is_end_stream(&self) -> bool {
        self.ahead.is_none() && (self.ended || self.inner.is_end_stream())
    }

    fn size_hint(&self) -> SizeHint {
        if self.ahead.is_some() {
            // Not exact any more: the frame ahead has left the inner body.
            SizeHint::default()
        } else {
            self.inner.size_hint()
        }
    }
}

/// A gRPC channel whose request bodies end with their last frame ([`Lookahead`]).
#[derive(Clone, Debug)]
pub struct EndStreamEarly<S>(pub S);

impl<S> Service<http::Request<tonic::body::Body>> for EndStreamEarly<S>
where
    S: Service<http::Request<tonic::body::Body>>,
{
    type Response = S::Response;
    type Error = S::Error;
    type Future = S::Future;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.0.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<tonic::body::Body>) -> Self::Future {
        self.0
            .call(request.map(|body| tonic::body::Body::new(Lookahead::new(body))))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tonic::codegen::Bytes;

    /// Yields its frames one by one; when `slow`, with a Pending before each
    /// (and before the end).
    struct Frames {
        frames: Vec<&'static str>,
        slow: bool,
        pending: bool,
    }

    impl Body for Frames {
        type Data = Bytes;
        type Error = std::convert::Infallible;

        fn poll_frame(
            self: Pin<&mut Self>,
            cx: &mut Context<'_>,
        ) -> Poll<Option<Result<Frame<Bytes>, Self::Error>>> {
            let this = self.get_mut();
            if this.slow && this.pending {
                this.pending = false;
                cx.waker().wake_by_ref();
                return Poll::Pending;
            }
            this.pending = true;
            if this.frames.is_empty() {
                return Poll::Ready(None);
            }
            Poll::Ready(Some(Ok(Frame::data(Bytes::from_static(
                this.frames.remove(0).as_bytes(),
            )))))
        }
    }

    fn frames<B: Body<Data = Bytes>>(body: B) -> Vec<(String, bool)>
    where
        B::Error: std::fmt::Debug,
    {
        let mut body = Box::pin(Lookahead::new(body));
        let mut cx = Context::from_waker(std::task::Waker::noop());
        let mut out = Vec::new();
        loop {
            match body.as_mut().poll_frame(&mut cx) {
                Poll::Pending => continue,
                Poll::Ready(None) => return out,
                Poll::Ready(Some(frame)) => {
                    let data = frame.unwrap().into_data().unwrap();
                    out.push((
                        String::from_utf8(data.to_vec()).unwrap(),
                        body.is_end_stream(),
                    ));
                }
            }
        }
    }

    fn body(frames: &[&'static str], slow: bool) -> Frames {
        Frames {
            frames: frames.to_vec(),
            slow,
            pending: true,
        }
    }

    #[test]
    fn the_last_frame_ends_the_stream_when_the_inner_body_is_ready() {
        assert_eq!(frames(body(&["tile"], false)), [("tile".into(), true)]);
        assert_eq!(
            frames(body(&["a", "b"], false)),
            [("a".into(), false), ("b".into(), true)]
        );
        assert!(frames(body(&[], false)).is_empty());
    }

    #[test]
    fn a_slow_body_gives_the_same_frames() {
        let got: Vec<String> = frames(body(&["a", "b"], true))
            .into_iter()
            .map(|(f, _)| f)
            .collect();
        assert_eq!(got, ["a", "b"]);
    }
}
