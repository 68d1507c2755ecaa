//! TLS for both servers (rustls): a certificate chain and key from PEM files, optionally a client
//! CA that every client certificate must chain to (mTLS for robots), and a reload of the files
//! (SIGHUP) that new connections see while open ones keep theirs.
use super::conn::Guarded;
use anyhow::{Context, Result};
use parking_lot::RwLock;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use std::io;
use std::path::PathBuf;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context as TaskContext, Poll};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};

/// Where the server's certificate, key and (for mTLS) client CA are.
#[derive(Clone, Debug)]
pub struct TlsFiles {
    pub cert: PathBuf,
    pub key: PathBuf,
    pub client_ca: Option<PathBuf>,
}

/// The current configurations (gRPC offers only h2; HTTP h2 and http/1.1).
pub struct Tls {
    files: TlsFiles,
    grpc: RwLock<Arc<rustls::ServerConfig>>,
    http: RwLock<Arc<rustls::ServerConfig>>,
}

fn load(files: &TlsFiles, alpn: &[&[u8]]) -> Result<rustls::ServerConfig> {
    let certs: Vec<CertificateDer<'static>> = CertificateDer::pem_file_iter(&files.cert)
        .and_then(|it| it.collect::<Result<_, _>>())
        .with_context(|| format!("reading certificates from {}", files.cert.display()))?;
    anyhow::ensure!(!certs.is_empty(), "no certificate in {}", files.cert.display());
    let key = PrivateKeyDer::from_pem_file(&files.key)
        .with_context(|| format!("reading a private key from {}", files.key.display()))?;
    // One provider named here: another crate enabling a second one cannot make this ambiguous.
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder =
        rustls::ServerConfig::builder_with_provider(provider.clone()).with_safe_default_protocol_versions()?;
    let builder = match &files.client_ca {
        None => builder.with_no_client_auth(),
        Some(ca) => {
            let mut roots = rustls::RootCertStore::empty();
            for cert in CertificateDer::pem_file_iter(ca).with_context(|| format!("reading {}", ca.display()))? {
                roots.add(cert.with_context(|| format!("reading {}", ca.display()))?)?;
            }
            let verifier = rustls::server::WebPkiClientVerifier::builder_with_provider(Arc::new(roots), provider)
                .build()
                .context("building the client certificate verifier")?;
            builder.with_client_cert_verifier(verifier)
        }
    };
    let mut cfg = builder.with_single_cert(certs, key).context("the certificate and key do not go together")?;
    cfg.alpn_protocols = alpn.iter().map(|p| p.to_vec()).collect();
    Ok(cfg)
}

impl Tls {
    pub fn load(files: TlsFiles) -> Result<Self> {
        let grpc = load(&files, &[b"h2"])?;
        let http = load(&files, &[b"h2", b"http/1.1"])?;
        Ok(Self { files, grpc: RwLock::new(Arc::new(grpc)), http: RwLock::new(Arc::new(http)) })
    }

    /// Reads the files again; on any error the configuration in use stays.
    pub fn reload(&self) -> Result<()> {
        let grpc = load(&self.files, &[b"h2"])?;
        let http = load(&self.files, &[b"h2", b"http/1.1"])?;
        *self.grpc.write() = Arc::new(grpc);
        *self.http.write() = Arc::new(http);
        Ok(())
    }

    pub fn acceptor(&self, grpc: bool) -> tokio_rustls::TlsAcceptor {
        let cfg = if grpc { self.grpc.read().clone() } else { self.http.read().clone() };
        tokio_rustls::TlsAcceptor::from(cfg)
    }
}

/// A client connection, with or without TLS.
pub enum Conn {
    Plain(Guarded),
    Tls(Box<tokio_rustls::server::TlsStream<Guarded>>),
}

impl Conn {
    /// Completes the TLS handshake when `tls` is set (within the connection's opening deadline:
    /// the guarded stream fails a read that waits past it).
    pub async fn open(io: Guarded, tls: Option<&Tls>, grpc: bool) -> io::Result<Self> {
        match tls {
            None => Ok(Conn::Plain(io)),
            Some(tls) => Ok(Conn::Tls(Box::new(tls.acceptor(grpc).accept(io).await?))),
        }
    }
}

impl AsyncRead for Conn {
    fn poll_read(self: Pin<&mut Self>, cx: &mut TaskContext<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Conn::Plain(s) => Pin::new(s).poll_read(cx, buf),
            Conn::Tls(s) => Pin::new(s.as_mut()).poll_read(cx, buf),
        }
    }
}

impl AsyncWrite for Conn {
    fn poll_write(self: Pin<&mut Self>, cx: &mut TaskContext<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        match self.get_mut() {
            Conn::Plain(s) => Pin::new(s).poll_write(cx, buf),
            Conn::Tls(s) => Pin::new(s.as_mut()).poll_write(cx, buf),
        }
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut TaskContext<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Conn::Plain(s) => Pin::new(s).poll_flush(cx),
            Conn::Tls(s) => Pin::new(s.as_mut()).poll_flush(cx),
        }
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut TaskContext<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Conn::Plain(s) => Pin::new(s).poll_shutdown(cx),
            Conn::Tls(s) => Pin::new(s.as_mut()).poll_shutdown(cx),
        }
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut TaskContext<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        match self.get_mut() {
            Conn::Plain(s) => Pin::new(s).poll_write_vectored(cx, bufs),
            Conn::Tls(s) => Pin::new(s.as_mut()).poll_write_vectored(cx, bufs),
        }
    }

    fn is_write_vectored(&self) -> bool {
        match self {
            Conn::Plain(s) => s.is_write_vectored(),
            Conn::Tls(s) => s.is_write_vectored(),
        }
    }
}

impl tonic::transport::server::Connected for Conn {
    type ConnectInfo = tonic::transport::server::TcpConnectInfo;

    fn connect_info(&self) -> Self::ConnectInfo {
        match self {
            Conn::Plain(s) => s.get_ref().connect_info(),
            Conn::Tls(s) => s.get_ref().0.get_ref().connect_info(),
        }
    }
}
