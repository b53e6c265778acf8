/// <reference types="vitest/config" />
import { defineConfig } from 'vite';

// The dashboard is served from any path (python -m services.web, or behind the nginx proxy).
export default defineConfig({
  base: './',
  build: { outDir: 'dist', emptyOutDir: true, chunkSizeWarningLimit: 1200 },
  test: { environment: 'node', include: ['test/**/*.test.ts'] },
});
