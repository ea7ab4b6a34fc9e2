//! The tiles on their way to the coordinator: one SubmitTiles stream a
//! message per tile each way, and the tile in flight while the next unit
//! renders.

use hypertexture_proto::pb;
use tonic::Status;

use crate::connection::Client;

/// A tile on its way to the coordinator: the reply may carry the next unit, and
/// the stream it went on comes back with it while the stream is still open.
pub(crate) type Sending =
    tokio::task::JoinHandle<(Option<TileStream>, Result<pb::SubmitTileResult, Status>)>;

/// A worker's tiles on one SubmitTiles stream: a message per tile each way,
/// without a call (headers, trailers, a new HTTP/2 stream) per unit.
pub(crate) struct TileStream {
    tiles: tokio::sync::mpsc::Sender<pb::SubmitTilesParams>,
    replies: tonic::Streaming<pb::SubmitTilesResult>,
}

impl TileStream {
    /// Opens a stream (one round trip: the coordinator answers at once).
    pub(crate) async fn open(client: &mut Client) -> Result<TileStream, Status> {
        // One tile is on a stream at a time: its reply is awaited before the next.
        let (tiles, queue) = tokio::sync::mpsc::channel(1);
        let replies = client
            .submit_tiles(tokio_stream::wrappers::ReceiverStream::new(queue))
            .await?
            .into_inner();
        Ok(TileStream { tiles, replies })
    }

    /// Sends a tile and waits for its reply. An error ends the stream: a
    /// refusal (as SubmitTile would refuse it) or a lost connection.
    async fn submit(&mut self, tile: pb::SubmitTileParams) -> Result<pb::SubmitTileResult, Status> {
        let closed = || Status::unavailable("the coordinator ended the tile stream");
        self.tiles
            .send(pb::SubmitTilesParams { tile: Some(tile) })
            .await
            .map_err(|_| closed())?;
        match self.replies.message().await? {
            Some(pb::SubmitTilesResult {
                result: Some(result),
            }) => Ok(result),
            Some(_) => Err(Status::internal("a SubmitTiles reply without its result")),
            None => Err(closed()),
        }
    }
}

/// Sends `tile` on `stream`, or on a new stream when there is none open.
pub(crate) fn send_tile(
    client: &Client,
    stream: Option<TileStream>,
    tile: pb::SubmitTileParams,
) -> Sending {
    let mut client = client.clone();
    tokio::spawn(async move {
        let mut stream = match stream {
            Some(stream) => stream,
            None => match TileStream::open(&mut client).await {
                Ok(stream) => stream,
                Err(status) => return (None, Err(status)),
            },
        };
        match stream.submit(tile).await {
            Ok(result) => (Some(stream), Ok(result)),
            Err(status) => (None, Err(status)),
        }
    })
}
