"""Pictures: scenes, trees and parses (`scene`), and grammar diagrams (`diagram`)."""
